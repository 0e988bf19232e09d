"""Fit time for a 3 h, 100 Hz channel with each base model.

One command: ``python bench/fit.py``. Simulates 1,080,000 samples of white + bias instability +
random walk (+ the model's extra term), computes the octave Allan curve once with the project's
engine, then times ``fit_allan`` per model: a full fit with profile-likelihood intervals, a
full fit with linearised intervals, and a refit from the previous result (what the live
analyzer does every few seconds). Reference measured in the same run: allantools computing
the same overlapping Allan curve (no model fit at all), so the fit's cost reads against the
cost of merely producing the curve with the common tool.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from imunoise.analysis.allan import oadev
from imunoise.analysis.fit import fit_allan
from imunoise.analysis.noise_stream import NoiseStream

FS = 100.0
N_SAMPLES = 3 * 3600 * 100
BASE = [("white", {"N": 3e-4}), ("bias_instability", {"B": 2e-5}), ("random_walk", {"K": 2e-7})]
MODELS = {
    "white": [],
    "white,random_walk": [],
    "white,bias_instability,random_walk": [],
    "quantization,white,bias_instability,random_walk": [("quantization", {"Q": 1e-6})],
    "white,gauss_markov,random_walk": [("gauss_markov", {"sigma": 5e-5, "T": 60.0})],
    "white,sinusoid,bias_instability,random_walk": [("sinusoid", {"A": 5e-4, "f": 3.3})],
    "white,random_walk,rate_ramp": [("rate_ramp", {"R": 1e-8})],
}


def _best_of(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> int:
    print(f"fit benchmark: {N_SAMPLES:,} samples at {FS:g} Hz (3 h), octave Allan curve")
    ref_time = None
    try:
        import allantools

        x = NoiseStream(BASE, FS, 0).take(N_SAMPLES)
        ref_time = _best_of(lambda: allantools.oadev(x, rate=FS, data_type="freq",
                                                     taus="octave"), repeat=1)
    except ImportError:
        pass
    print(f"{'model':50s} {'curve':>8s} {'fit+profile':>12s} {'fit+jacobian':>13s} "
          f"{'refit':>8s}  chi2/dof")
    worst = 0.0
    for name, extra in MODELS.items():
        x = NoiseStream(BASE + extra, FS, 1).take(N_SAMPLES)
        t = time.perf_counter()
        curve = oadev(x, FS, m="octave")
        t_curve = time.perf_counter() - t
        res = fit_allan(curve, name)
        t_prof = _best_of(lambda n=name, c=curve: fit_allan(c, n))
        t_jac = _best_of(lambda n=name, c=curve: fit_allan(c, n, intervals="jacobian"))
        t_refit = _best_of(lambda n=name, c=curve, r=res: fit_allan(c, n, start=r,
                                                                  intervals="jacobian"))
        worst = max(worst, t_prof)
        print(f"{name:50s} {t_curve:7.2f}s {t_prof:11.3f}s {t_jac:12.3f}s {t_refit:7.3f}s  "
              f"{res.chi2_per_dof:.2f}")
    if ref_time is not None:
        print(f"reference: allantools.oadev of the same channel (curve only, no model): "
              f"{ref_time:.2f} s; slowest full fit here (profile intervals): {worst:.3f} s, "
              f"{worst / ref_time:.1f} times the cost of that curve")
    return 0


if __name__ == "__main__":
    sys.exit(main())
