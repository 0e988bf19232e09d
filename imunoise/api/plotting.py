"""Matplotlib drawings of the API's results (the ``plot`` extra, imported only when a result
is plotted)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from imunoise.extras import require


def axes(ax: Any = None) -> Any:
    """``ax``, or the axes of a new figure; :class:`imunoise.extras.MissingExtra` without
    matplotlib."""
    require("plot", "plot()")
    if ax is not None:
        return ax
    import matplotlib.pyplot as plt

    _, ax = plt.subplots(figsize=(6.4, 4.4), layout="constrained")
    return ax


def allan(ax: Any, tau_s: np.ndarray, adev: np.ndarray, low: np.ndarray, high: np.ndarray,
          units: str, label: str) -> None:
    """A measured Allan deviation with its confidence band, on log axes."""
    line, = ax.loglog(tau_s, adev, "o-", ms=3, label=label)
    ax.fill_between(tau_s, low, high, color=line.get_color(), alpha=0.2, lw=0,
                    label=_band_label(ax))
    ax.set_xlabel("averaging time tau [s]")
    ax.set_ylabel(f"Allan deviation [{units}]" if units else "Allan deviation")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def model(ax: Any, tau_s: np.ndarray, adev: np.ndarray, terms: Mapping[str, np.ndarray]
          ) -> None:
    """A fitted model's Allan deviation and each term's, over a measured curve (the axes keep
    the measurement's range: a term far below it, e.g. an unresolved one, leaves the plot)."""
    ylim = ax.get_ylim()
    ax.loglog(tau_s, adev, "k-", lw=1.5, label="model")
    for name, curve in terms.items():
        ax.loglog(tau_s, curve, "--", lw=1, label=name)
    ax.set_ylim(ylim)
    ax.legend(loc="best", fontsize="small")


def run(ax: Any, tau_s: np.ndarray, adev: np.ndarray, model_adev: np.ndarray, units: str,
        label: str) -> None:
    """One run of several: its measured Allan deviation (points) and its model's (a line of
    the same colour), on log axes."""
    line, = ax.loglog(tau_s, adev, "o", ms=3, label=label)
    ax.loglog(tau_s, model_adev, "-", lw=1, color=line.get_color())
    ax.set_xlabel("averaging time tau [s]")
    ax.set_ylabel(f"Allan deviation [{units}]" if units else "Allan deviation")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def psd(ax: Any, f_hz: np.ndarray, value: np.ndarray, low: np.ndarray, high: np.ndarray,
        units: str, label: str) -> None:
    """A one-sided PSD with its confidence band, on log axes."""
    line, = ax.loglog(f_hz, value, "-", lw=1, label=label)
    ax.fill_between(f_hz, low, high, color=line.get_color(), alpha=0.2, lw=0,
                    label=_band_label(ax))
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(f"PSD [({units})^2/Hz]" if units else "PSD [1/Hz]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def _band_label(ax: Any) -> str:
    """The legend entry of a confidence band: once per axes."""
    shown = [c.get_label() for c in ax.collections]
    return "_nolegend_" if "95 % interval" in shown else "95 % interval"
