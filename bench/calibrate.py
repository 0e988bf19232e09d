"""Calibration of the diagnosis on simulated records, 40 seeds per case (not a timing).

Each record is 2 h at 50 Hz of white noise (N 3e-4), flicker (B 5e-5) and rate random walk
(K 2e-6) at a MEMS gyro's levels, plus one element the given model lacks. For each case it
counts the seeds where that element is the top suggestion and significant, and those where
the true parameters also lie inside the suggestion's 95 % intervals; the targets are 90 % of
seeds named first and significant, and coverage in 90-98 % of seeds. The null cases give the
correct model (plain, with a 4-tap moving-average output filter, with 20 runs of lost
samples) and count the seeds where anything is significant (target: at most 5 %) and the
mean of each error part: Allan chi2/dof, PSD deviance per bin and hold-out chi2/dof (target:
1 +- 0.3 each).

Run: python bench/calibrate.py [--cases a,b] [--seeds 40] [--workers 2]
Cases: moving_average lowpass resonance gauss_markov_30 gauss_markov_100 sinusoid warmup bias_step
null_plain null_filter null_lost (default: all; about 15 min on two cores).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one worker per core

import numpy as np  # noqa: E402

from imunoise.analysis.diagnosis import diagnose  # noqa: E402
from imunoise.analysis.noise_stream import simulate  # noqa: E402

FS = 50.0
N = int(2 * 3600 * FS)
BASE = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
        ("random_walk", {"K": 2e-6})]
GIVEN = ["white", "bias_instability", "random_walk"]
T_STEP, STEP = 3030.0, 1.2e-3          # s, rad/s: a knock 50.5 min in
T_WARM, WARM = 300.0, 1.5e-3           # s, rad/s: settling after power-on
F_LINE, A_LINE = 0.55, 2e-4             # Hz, rad/s: a bench line (a pump, a fan)


def _gm2(t2: float) -> tuple:
    model = BASE + [("gauss_markov", {"sigma": 2e-4, "T": 1.0}),
                    ("gauss_markov", {"sigma": 2e-4, "T": t2})]

    def truth(params: dict[str, float]) -> dict[str, float]:
        # the suggestion may name either time constant; compare with the one it found
        return {"T": t2 if params.get("T", 0.0) > t2 ** 0.5 else 1.0}
    return model, GIVEN + ["gauss_markov"], "gauss_markov", truth


# case: (simulated terms, given model, expected top term, truth of its parameters, added
# deterministic signal of time t_s, seed offset)
CASES: dict[str, tuple] = {
    "moving_average": (BASE + [("moving_average", {"taps": 4})], GIVEN, "moving_average",
                       lambda p: {"taps": 4.0}, None, 0),
    "lowpass": (BASE + [("lowpass", {"fc": 3.0})], GIVEN, "lowpass",
                lambda p: {"fc": 3.0}, None, 0),
    "resonance": (BASE + [("resonance", {"sigma": 3e-4, "f0": 6.0, "Q": 3.0})], GIVEN,
                  "resonance", lambda p: {"sigma": 3e-4, "f0": 6.0, "Q": 3.0}, None, 0),
    "gauss_markov_30": (*_gm2(30.0), None, 0),
    "gauss_markov_100": (*_gm2(100.0), None, 0),
    "sinusoid": (BASE, GIVEN, "sinusoid", lambda p: {"A": A_LINE, "f": F_LINE},
                 lambda t: A_LINE * np.sin(2.0 * np.pi * F_LINE * t + 0.3), 900),
    "warmup": (BASE, GIVEN, "warmup", lambda p: {"tau_s": T_WARM, "amplitude": WARM},
               lambda t: WARM * np.exp(-t / T_WARM), 700),
    "bias_step": (BASE, GIVEN, "bias_step", lambda p: {"t_s": T_STEP, "size": STEP},
                  lambda t: STEP * (t >= T_STEP), 700),
}
NULLS = ("null_plain", "null_filter", "null_lost")


def _element(case: str, seed: int) -> tuple[bool, bool, str]:
    model, given, term, truth, add, offset = CASES[case]
    x = simulate(model, N, FS, rng=offset + seed)
    if add is not None:
        x = x + add(np.arange(N) / FS)
    top = diagnose(x, FS, given).suggestions[0]
    named = top.term == term and top.significant
    inside = named and all(
        top.ci95.get(k, (np.inf, -np.inf))[0] <= v <= top.ci95.get(k, (np.inf, -np.inf))[1]
        for k, v in truth(top.params).items())
    return named, inside, f"{top.term}{'' if top.significant else ' (not significant)'}"


def _null(case: str, seed: int) -> tuple[bool, tuple[float, float, float], str]:
    variant = case.removeprefix("null_")
    model = BASE + ([("moving_average", {"taps": 4})] if variant == "filter" else [])
    given = GIVEN + (["moving_average:taps=4"] if variant == "filter" else [])
    x = simulate(model, N, FS, rng=1000 + seed)
    starts = None
    if variant == "lost":
        keep = np.ones(N, bool)
        rng = np.random.default_rng(seed)
        for a in rng.integers(0, N - 100, 20):
            keep[a:a + rng.integers(1, 50)] = False
        idx = np.flatnonzero(keep)
        starts = np.concatenate(([0], np.flatnonzero(np.diff(idx) > 1) + 1))
        x = x[keep]
    d = diagnose(x, FS, given, segment_starts=starts)
    flagged = [s.term for s in d.suggestions if s.significant]
    psd = (d.error_parts.get("psd") or {}).get("deviance_per_bin")
    holdout = (d.error_parts.get("holdout") or {}).get("chi2_per_dof")
    parts = (float(d.fit.chi2_per_dof), float("nan") if psd is None else float(psd),
             float("nan") if holdout is None else float(holdout))
    return bool(flagged), parts, ",".join(flagged) or "-"


def _run(job: tuple[str, int]) -> tuple[str, int, tuple]:
    case, seed = job
    fn: Callable = _null if case in NULLS else _element
    return case, seed, fn(case, seed)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join([*CASES, *NULLS]),
                    help="comma-separated cases (default: all)")
    ap.add_argument("--seeds", type=int, default=40, help="seeds per case (default: 40)")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                    help="worker processes (default: %(default)s)")
    a = ap.parse_args()
    cases = [c for c in a.cases.split(",") if c]
    unknown = [c for c in cases if c not in CASES and c not in NULLS]
    if unknown:
        print(f"error: unknown case(s) {', '.join(unknown)}", file=sys.stderr)
        return 2
    jobs = [(c, s) for c in cases for s in range(a.seeds)]
    results: dict[str, list] = {c: [] for c in cases}
    t0 = time.perf_counter()
    with ProcessPoolExecutor(a.workers) as pool:
        for i, (case, _seed, out) in enumerate(pool.map(_run, jobs), 1):
            results[case].append(out)
            print(f"\r{i}/{len(jobs)} records diagnosed, {time.perf_counter() - t0:.0f} s",
                  end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    n = a.seeds
    print(f"diagnosis calibration: {n} seeds of 2 h at {FS:g} Hz per case")
    for case in cases:
        rows = results[case]
        if case in NULLS:
            flagged = sum(r[0] for r in rows)
            allan, psd, holdout = np.nanmean(np.array([r[1] for r in rows]), axis=0)
            print(f"  {case:17s} anything significant {flagged:2d}/{n} (target <= {0.05 * n:g})"
                  f"  mean error parts (target 1 +- 0.3 each): allan {allan:.2f}, psd "
                  f"{psd:.2f}, hold-out {holdout:.2f}")
        else:
            named = sum(r[0] for r in rows)
            inside = sum(r[1] for r in rows)
            others = sorted({r[2] for r in rows if not r[0]})
            print(f"  {case:17s} named first and significant {named:2d}/{n} "
                  f"(target >= {0.9 * n:g}), truth inside its 95 % intervals {inside:2d}/{n}"
                  + (f"; otherwise: {'; '.join(others)}" if others else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
