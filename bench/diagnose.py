"""Diagnose speed: a real channel through the command line, and a filtered simulated record.

Run from the repository root:

    python bench/diagnose.py              # all three figures, best of 3 (several minutes)
    python bench/diagnose.py --repeat 1   # one run each
    python bench/diagnose.py --only real  # the real channel alone (or: sim, sim_filter)

1. ``real``: ``imunoise diagnose FILE --channel accel_x --model
   white,bias_instability,random_walk --json`` on ADIS16405 run 1 (../shared/data/adis16405,
   1e6 samples at 100 Hz, converted once to CSV in a temporary folder), as a user runs it: wall
   time of the whole command (start-up, reading, diagnosis, JSON). Target: at most 5 s.
2. ``sim``: one diagnosis round (:func:`imunoise.analysis.diagnosis.diagnose`, in this process)
   of a simulated 3 h, 100 Hz record whose noise passed a 4-tap moving average, with the base
   model white,bias_instability,random_walk.
3. ``sim_filter``: the same record with ``moving_average`` (taps fitted) in the model.

``imunoise diagnose`` refits the candidate terms, the hold-out halves and the profile
intervals in worker processes, one per CPU of its affinity mask
(:func:`imunoise.pipeline.workers.cpu_job_map`), and computes the other channels' coherence
in a background process meanwhile; the ``sim`` figures pass the same job map to
:func:`~imunoise.analysis.diagnosis.diagnose`, and the header line says how many that is.
Each process keeps its linear algebra on one thread (the command line's default too).

The machine may be shared: each figure is the median of ``--repeat`` runs, wall and CPU time
(user + system, the command's own for ``real``), and beside it, as the reference measured in
the same run, allantools' overlapping Allan deviation of the same samples at octave taus (a
curve only: no model, no diagnosis) and the ratios of the two, which move less with the
machine's load than the seconds do.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as the targets say

import argparse  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
ADIS = REPO.parent / "shared" / "data" / "adis16405" / "run1.npz"
FS = 100.0
N_SIM = int(3 * 3600 * FS)
TARGET_S = 5.0
BASE = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
        ("random_walk", {"K": 2e-6})]
GIVEN = "white,bias_instability,random_walk"


def _cpu() -> float:
    """CPU seconds (user + system) of this process and of its finished children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _median_time(fn, repeat: int) -> tuple[tuple[float, float], list[float], object]:
    """``((median wall s, median CPU s), wall times, last result)`` of ``repeat`` runs."""
    walls, cpus, out = [], [], None
    for _ in range(repeat):
        c0, t0 = _cpu(), time.perf_counter()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(_cpu() - c0)
    return (statistics.median(walls), statistics.median(cpus)), walls, out


def _reference(x: np.ndarray, repeat: int) -> tuple[float, float] | None:
    """Median (wall, CPU) time of allantools.oadev at octave taus on ``x``, or None."""
    try:
        import allantools
    except ImportError:
        return None
    taus = 2.0 ** np.arange(0, int(np.log2(x.size / 4))) / FS
    t, _, _ = _median_time(
        lambda: allantools.oadev(x, rate=FS, data_type="freq", taus=taus), repeat)
    return t


def _line(label: str, t: tuple[float, float], walls: list[float],
          ref: tuple[float, float] | None, target: bool) -> None:
    runs = ", ".join(f"{v:.2f}" for v in walls)
    text = f"{label}: {t[0]:.2f} s wall (median of [{runs}]), {t[1]:.2f} s CPU"
    if target:
        text += f" (target <= {TARGET_S:g} s wall: {'met' if t[0] <= TARGET_S else 'MISSED'})"
    print(text)
    if ref is not None:
        print(f"    reference allantools.oadev, octave taus, same samples: {ref[0]:.2f} s wall, "
              f"{ref[1]:.2f} s CPU; ratio {t[0] / ref[0]:.1f} (wall), {t[1] / ref[1]:.1f} (CPU)")


def bench_real(repeat: int) -> None:
    if not ADIS.exists():
        print(f"real: {ADIS} absent, skipped")
        return
    d = np.load(ADIS)
    accel = d["accel_counts"] * float(d["accel_scale_g"]) * 9.80665
    gyro = d["gyro_counts"] * float(d["gyro_scale_dps"]) * math.pi / 180.0
    fs = float(d["fs_hz"])
    names = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "adis16405_run1.csv"
        t = np.arange(len(accel)) / fs
        cols = [gyro[:, i] for i in range(3)] + [accel[:, i] for i in range(3)]
        np.savetxt(path, np.column_stack([t] + cols), delimiter=",", comments="",
                   header="t," + ",".join(names), fmt="%.10g")
        exe = Path(sys.executable).with_name("imunoise")
        cmd = [str(exe) if exe.exists() else sys.executable] + \
            ([] if exe.exists() else ["-m", "imunoise.cli"]) + \
            ["diagnose", str(path), "--channel", "accel_x", "--model", GIVEN, "--json"]

        # every run parses the CSV afresh: the record cache would otherwise serve the
        # repeats, and the figure is that of a first diagnosis of a new recording
        env = {**os.environ, "IMUNOISE_CACHE_MB": "0"}

        def run() -> str:
            p = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
            return p.stdout

        t_med, times, _ = _median_time(run, repeat)
    _line("real  ADIS16405 run 1 accel_x, `imunoise diagnose --json`, 1e6 samples",
          t_med, times, _reference(accel[:, 0].astype(np.float64), repeat), True)


def _sim_record() -> np.ndarray:
    from imunoise.analysis.noise_stream import simulate

    return simulate(BASE + [("moving_average", {"taps": 4})], N_SIM, FS, rng=1)


def bench_sim(repeat: int, with_filter: bool, x: np.ndarray) -> None:
    from imunoise.analysis.diagnosis import diagnose
    from imunoise.pipeline.workers import cpu_job_map

    model = GIVEN + (",moving_average" if with_filter else "")
    t_med, times, d = _median_time(
        lambda: diagnose(x, FS, model, job_map=cpu_job_map()), repeat)
    label = (f"sim   3 h at 100 Hz through a 4-tap moving average, one round, model {model}")
    _line(label, t_med, times, _reference(x, repeat), False)
    top = d.suggestions[0] if d.suggestions else None
    if top is not None:
        print(f"    first suggestion: {top.term} (significant: {top.significant}), chi2/dof "
              f"{top.chi2_per_dof_before:.3g} -> {top.chi2_per_dof_after:.3g}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure (median)")
    parser.add_argument("--only", choices=("real", "sim", "sim_filter"), action="append",
                        help="run only these figures (repeatable)")
    args = parser.parse_args()
    only = set(args.only or ("real", "sim", "sim_filter"))
    from imunoise.pipeline.workers import available_cpus

    print(f"diagnosis workers: {available_cpus()} (the CPUs of this process's affinity)")
    if "real" in only:
        bench_real(args.repeat)
    if only & {"sim", "sim_filter"}:
        x = _sim_record()
        if "sim" in only:
            bench_sim(args.repeat, False, x)
        if "sim_filter" in only:
            bench_sim(args.repeat, True, x)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
