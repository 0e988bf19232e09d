"""PSD speed: batch log-frequency PSD and the streaming estimator against scipy.signal.welch.

Prints samples per second for 10^7 samples (27.8 h at 100 Hz) and the ratio to one plain Welch
pass (scipy, Hann 256, 50 %), which covers only the top band on a linear axis.
Run: python bench/bench_psd.py
"""

from __future__ import annotations

import time

import numpy as np
import scipy.signal

from imunoise.analysis.psd import StreamingPsd, log_psd

FS = 100.0
N = 10_000_000


def _best(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    x = np.random.default_rng(0).normal(size=N)
    t_welch = _best(lambda: scipy.signal.welch(x, FS, window="hann", nperseg=256, noverlap=128))
    t_log = _best(lambda: log_psd(x, FS))
    est = log_psd(x, FS)

    def stream() -> None:
        s = StreamingPsd(FS)
        for a in range(0, N, 1000):
            s.update(x[a:a + 1000])
        s.estimate()

    t_stream = _best(stream, repeat=1)
    print(f"samples: {N:,} at {FS:g} Hz ({N / FS / 3600:.1f} h); log_psd points: {len(est)}, "
          f"{est.f_hz[0]:.2e} .. {est.f_hz[-1]:.3g} Hz")
    print(f"scipy.signal.welch (reference, top band only): {t_welch:.2f} s "
          f"({N / t_welch / 1e6:.1f} M samples/s)")
    print(f"log_psd (batch cascade, full band):            {t_log:.2f} s "
          f"({N / t_log / 1e6:.1f} M samples/s, {t_log / t_welch:.2f}x welch)")
    print(f"StreamingPsd, blocks of 1000 samples:          {t_stream:.2f} s "
          f"({N / t_stream / 1e6:.1f} M samples/s, {t_stream / t_welch:.2f}x welch)")


if __name__ == "__main__":
    main()
