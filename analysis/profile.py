"""Profile-likelihood interval end points by bracketing and bisection.

Shared by the Allan-curve fit and the block likelihood: both move one (log-)parameter away from
its best value, re-optimising the others, until the objective rises past a threshold.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

Excess = Callable[[float, np.ndarray], tuple[float, np.ndarray]]
"""``excess(value, guess) -> (rise of the objective, optimised other parameters)``."""


def profile_bounds(excess: Excess, best: float, lo: float, hi: float, step: float,
                   threshold: float, guess: np.ndarray, bisections: int,
                   max_doublings: int = 12, width: float | None = None,
                   max_bisections: int = 24) -> tuple[float, float]:
    """Lower and upper end of ``{v : excess(v) <= threshold}`` around ``best``.

    From ``best`` the search steps outwards, doubling ``step`` each time, until the rise
    exceeds ``threshold`` or the parameter's bound (``lo`` or ``hi``) is reached; an end that
    never exceeds it is the bound itself. The bracket is then narrowed by ``bisections``
    halvings, and further (up to ``max_bisections`` in all) while it is wider than ``width``,
    and its midpoint returned. The other parameters' optimum found at each accepted point
    seeds the next evaluation.

    ``width`` matters for a parameter the data do not need: its best value sits at the bottom
    of its range, tens of log units below where the objective starts to rise, so the doubling
    steps end in a bracket many units wide, which a fixed number of halvings leaves wide
    enough to move the end found by a factor of two with the start.
    """
    out = []
    for direction, bound in ((-1.0, lo), (1.0, hi)):
        inside, g, outside, s = best, guess, None, step
        for _ in range(max_doublings):
            v = float(np.clip(inside + direction * s, min(bound, best), max(bound, best)))
            e, g_new = excess(v, g)
            if e > threshold:
                outside = v
                break
            inside, g = v, g_new
            if v == bound:
                break
            s *= 2.0
        if outside is None:
            out.append(float(bound))
            continue
        done = 0
        while done < bisections or (width is not None and abs(outside - inside) > width
                                    and done < max_bisections):
            done += 1
            mid = 0.5 * (inside + outside)
            e, g_new = excess(mid, g)
            if e > threshold:
                outside = mid
            else:
                inside, g = mid, g_new
        out.append(0.5 * (inside + outside))
    return out[0], out[1]
