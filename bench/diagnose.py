"""Diagnose speed: one 3 h, 100 Hz gyro channel (1.08 million samples) on one core.

Times the whole diagnosis (Allan curve, fit of the given model, refit with every missing
term, spectral lines, drift, temperature, windows, outliers) of a record with a hidden
sinusoid, and, as the reference measured in the same run, allantools' overlapping Allan
deviation of the same samples at octave taus (a curve only: no model, no diagnosis).
Target: under 5 s.
Run: python bench/diagnose.py
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as the target says

import time  # noqa: E402

import numpy as np  # noqa: E402

from imunoise.analysis.diagnosis import diagnose  # noqa: E402
from imunoise.analysis.noise_stream import simulate  # noqa: E402

FS = 100.0
N = int(3 * 3600 * FS)
TARGET_S = 5.0
MODEL = [("white", {"N": 3e-4}), ("bias_instability", {"B": 3e-5}),
         ("random_walk", {"K": 3e-6}), ("sinusoid", {"A": 2e-4, "f": 2.7})]


def _best(fn, repeat: int = 3) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    t = np.arange(N) / FS
    temp = 25.0 + 5.0 * (1 - np.exp(-t / 1800.0))
    x = simulate(MODEL, N, FS, rng=1)
    given = ["white", "bias_instability", "random_walk"]
    t_diag, d = _best(lambda: diagnose(x, FS, given, temperature=(t[::100], temp[::100])))
    top = d.suggestions[0]
    print(f"diagnose, {N:,} samples (3 h at 100 Hz), one core: {t_diag:.2f} s "
          f"(target < {TARGET_S:g} s: {'met' if t_diag < TARGET_S else 'MISSED'})")
    print(f"  first suggestion: {top.term} (significant: {top.significant}), chi2/dof "
          f"{top.chi2_per_dof_before:.3g} -> {top.chi2_per_dof_after:.3g}")
    try:
        import allantools
    except ImportError:
        print("  allantools not installed: no reference timing")
        return
    taus = 2.0 ** np.arange(0, int(np.log2(N / 4))) / FS
    t_ref, _ = _best(lambda: allantools.oadev(x, rate=FS, data_type="freq", taus=taus))
    print(f"  reference: allantools.oadev at {taus.size} octave taus (curve only): "
          f"{t_ref:.2f} s; diagnosis / curve = {t_diag / t_ref:.2f}")


if __name__ == "__main__":
    main()
