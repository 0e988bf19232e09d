"""A small plotter that writes self-contained inline SVG (log-log or log-linear axes).

Built for the HTML report: no fonts, scripts or style sheets from outside, so the file opens
with no network. Supports decade axes with minor ticks, linear axes with round-number ticks,
axis labels with units, shaded bands (confidence intervals) as polygons, lines (split at
missing values), markers with optional vertical error bars, horizontal reference lines and a
legend.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from html import escape

import numpy as np

_CLIP_IDS = itertools.count(1)  # clip-path ids unique within one process (one report)

PALETTE = ("#1f4e9c", "#c0392b", "#2e8b57", "#8e44ad", "#d35400", "#16a085", "#7f8c8d",
           "#b7950b", "#2c3e50", "#e84393")


@dataclass
class _Item:
    kind: str  # "band" | "line" | "markers" | "hline"
    label: str | None
    color: str
    x: np.ndarray
    y: np.ndarray
    y2: np.ndarray | None = None  # band upper edge or error-bar upper end
    y0: np.ndarray | None = None  # error-bar lower end
    width: float = 1.6
    dash: str | None = None
    opacity: float = 0.25
    autoscale: bool = True  # whether the item's values set the axis ranges


@dataclass
class Plot:
    """One chart. Add items, then call :meth:`svg`.

    Attributes:
        title: heading drawn above the plot area.
        x_label, y_label: axis labels, including units, e.g. ``"averaging time tau (s)"``.
        x_log, y_log: logarithmic axes (base 10) when true.
        width, height: size of the SVG in px.
    """

    title: str
    x_label: str
    y_label: str
    x_log: bool = True
    y_log: bool = True
    width: int = 760
    height: int = 420
    items: list[_Item] = field(default_factory=list)
    _next_color: int = 0

    def _color(self, color: str | None) -> str:
        if color:
            return color
        c = PALETTE[self._next_color % len(PALETTE)]
        self._next_color += 1
        return c

    def band(self, x, lo, hi, label: str | None = None, color: str | None = None,
             opacity: float = 0.22) -> Plot:
        """Shaded region between ``lo`` and ``hi`` (e.g. a confidence interval)."""
        self.items.append(_Item("band", label, self._color(color), _arr(x), _arr(lo), _arr(hi),
                                opacity=opacity))
        return self

    def line(self, x, y, label: str | None = None, color: str | None = None,
             width: float = 1.6, dash: str | None = None, autoscale: bool = True) -> Plot:
        """Polyline through the points; broken where a value is missing or not drawable.

        With ``autoscale=False`` the line does not widen the y range (a negligible model term
        far below the data is clipped rather than squeezing the data into a corner).
        """
        self.items.append(_Item("line", label, self._color(color), _arr(x), _arr(y),
                                width=width, dash=dash, autoscale=autoscale))
        return self

    def markers(self, x, y, label: str | None = None, color: str | None = None,
                err_lo=None, err_hi=None) -> Plot:
        """Dots, optionally with vertical error bars from ``err_lo`` to ``err_hi``."""
        self.items.append(_Item("markers", label, self._color(color), _arr(x), _arr(y),
                                y2=None if err_hi is None else _arr(err_hi),
                                y0=None if err_lo is None else _arr(err_lo)))
        return self

    def hline(self, y: float, label: str | None = None, color: str = "#555555",
              dash: str | None = "4 3") -> Plot:
        """Horizontal reference line across the plot area."""
        self.items.append(_Item("hline", label, color, np.array([]), np.array([float(y)]),
                                width=1.0, dash=dash))
        return self

    # -- rendering ---------------------------------------------------------------------------

    def svg(self) -> str:
        """The chart as an ``<svg>`` element string."""
        left, right, top, bottom = 78, 190, 34, 52
        pw, ph = self.width - left - right, self.height - top - bottom
        xr = self._range("x")
        yr = self._range("y")
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" class="plot" width="{self.width}" '
               f'height="{self.height}" viewBox="0 0 {self.width} {self.height}" role="img" '
               f'aria-label="{escape(self.title)}" font-family="sans-serif" font-size="12">',
               f'<title>{escape(self.title)}</title>',
               f'<rect x="0" y="0" width="{self.width}" height="{self.height}" fill="#ffffff"/>',
               f'<text x="{left + pw / 2:.1f}" y="20" text-anchor="middle" font-size="14" '
               f'font-weight="bold">{escape(self.title)}</text>']
        if xr is None or yr is None:
            out.append(f'<text x="{left + pw / 2:.1f}" y="{top + ph / 2:.1f}" '
                       'text-anchor="middle" fill="#888">no data</text></svg>')
            return "".join(out)

        def sx(v: np.ndarray) -> np.ndarray:
            t = _tf(v, self.x_log)
            return left + (t - xr[0]) / (xr[1] - xr[0]) * pw

        def sy(v: np.ndarray) -> np.ndarray:
            t = _tf(v, self.y_log)
            return top + ph - (t - yr[0]) / (yr[1] - yr[0]) * ph

        out.append(f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="#fcfcfc" '
                   'stroke="#333" stroke-width="1"/>')
        out.extend(self._grid(xr, yr, left, top, pw, ph))
        clip = f"plotclip{next(_CLIP_IDS)}"
        out.append(f'<clipPath id="{clip}"><rect x="{left}" y="{top}" width="{pw}" '
                   f'height="{ph}"/></clipPath><g clip-path="url(#{clip})">')
        for it in self.items:
            out.extend(self._draw(it, sx, sy, left, pw))
        out.append("</g>")
        out.append(f'<text x="{left + pw / 2:.1f}" y="{self.height - 10}" '
                   f'text-anchor="middle">{escape(self.x_label)}</text>')
        out.append(f'<text transform="translate(16 {top + ph / 2:.1f}) rotate(-90)" '
                   f'text-anchor="middle">{escape(self.y_label)}</text>')
        out.extend(self._legend(left + pw + 12, top))
        out.append("</svg>")
        return "".join(out)

    def _range(self, axis: str) -> tuple[float, float] | None:
        log = self.x_log if axis == "x" else self.y_log
        vals = []
        for it in self.items:
            if axis == "x":
                vals.append(it.x)
            elif it.autoscale:
                vals.extend(a for a in (it.y, it.y2, it.y0) if a is not None)
        if not vals:
            return None
        v = np.concatenate([np.ravel(a) for a in vals])
        v = v[np.isfinite(v) & ((v > 0) if log else True)]
        if v.size == 0:
            return None
        lo, hi = float(v.min()), float(v.max())
        if log:
            lo, hi = math.log10(lo), math.log10(hi)
            if hi - lo < 1e-9:
                lo, hi = lo - 0.5, hi + 0.5
            pad = 0.04 * (hi - lo)
            return lo - pad, hi + pad
        if hi - lo < 1e-300:
            lo, hi = lo - 1.0, hi + 1.0
        pad = 0.06 * (hi - lo)
        return lo - pad, hi + pad

    def _grid(self, xr, yr, left, top, pw, ph) -> list[str]:
        out = []
        for axis, (lo, hi), log in (("x", xr, self.x_log), ("y", yr, self.y_log)):
            for pos, label, major in _ticks(lo, hi, log):
                frac = (pos - lo) / (hi - lo)
                if axis == "x":
                    px = left + frac * pw
                    out.append(f'<line x1="{px:.1f}" y1="{top}" x2="{px:.1f}" y2="{top + ph}" '
                               f'stroke="{"#d0d0d0" if major else "#ececec"}" '
                               'stroke-width="1"/>')
                    out.append(f'<line x1="{px:.1f}" y1="{top + ph}" x2="{px:.1f}" '
                               f'y2="{top + ph + (6 if major else 3)}" stroke="#333"/>')
                    if label:
                        out.append(f'<text x="{px:.1f}" y="{top + ph + 20}" '
                                   f'text-anchor="middle">{label}</text>')
                else:
                    py = top + ph - frac * ph
                    out.append(f'<line x1="{left}" y1="{py:.1f}" x2="{left + pw}" '
                               f'y2="{py:.1f}" stroke="{"#d0d0d0" if major else "#ececec"}" '
                               'stroke-width="1"/>')
                    out.append(f'<line x1="{left - (6 if major else 3)}" y1="{py:.1f}" '
                               f'x2="{left}" y2="{py:.1f}" stroke="#333"/>')
                    if label:
                        out.append(f'<text x="{left - 9}" y="{py + 4:.1f}" '
                                   f'text-anchor="end">{label}</text>')
        return out

    def _draw(self, it: _Item, sx, sy, left: float, pw: float) -> list[str]:
        dash = f' stroke-dasharray="{it.dash}"' if it.dash else ""
        if it.kind == "hline":
            py = float(sy(it.y)[0])
            if not np.isfinite(py):
                return []
            return [f'<line x1="{left}" y1="{py:.1f}" x2="{left + pw}" y2="{py:.1f}" '
                    f'stroke="{it.color}" stroke-width="{it.width}"{dash}/>']
        ok = self._drawable(it.x, self.x_log) & self._drawable(it.y, self.y_log)
        if it.kind == "band":
            ok &= self._drawable(it.y2, self.y_log)
            out = []
            for run in _runs(ok):
                xs, lo, hi = sx(it.x[run]), sy(it.y[run]), sy(it.y2[run])
                pts = [f"{a:.1f},{b:.1f}" for a, b in zip(xs, hi, strict=True)]
                pts += [f"{a:.1f},{b:.1f}" for a, b in zip(xs[::-1], lo[::-1], strict=True)]
                out.append(f'<polygon points="{" ".join(pts)}" fill="{it.color}" '
                           f'fill-opacity="{it.opacity}" stroke="none"/>')
            return out
        if it.kind == "line":
            out = []
            for run in _runs(ok):
                if run.size < 2:
                    continue
                pts = " ".join(f"{a:.1f},{b:.1f}"
                               for a, b in zip(sx(it.x[run]), sy(it.y[run]), strict=True))
                out.append(f'<polyline points="{pts}" fill="none" stroke="{it.color}" '
                           f'stroke-width="{it.width}" stroke-linejoin="round"{dash}/>')
            return out
        out = []
        idx = np.flatnonzero(ok)
        xs, ys = sx(it.x[idx]), sy(it.y[idx])
        if it.y0 is not None and it.y2 is not None:
            eok = self._drawable(it.y0[idx], self.y_log) & self._drawable(it.y2[idx], self.y_log)
            e0, e2 = sy(it.y0[idx]), sy(it.y2[idx])
            for a, b, c, good in zip(xs, e0, e2, eok, strict=True):
                if good:
                    out.append(f'<line x1="{a:.1f}" y1="{b:.1f}" x2="{a:.1f}" y2="{c:.1f}" '
                               f'stroke="{it.color}" stroke-width="1"/>')
        for a, b in zip(xs, ys, strict=True):
            out.append(f'<circle cx="{a:.1f}" cy="{b:.1f}" r="2.6" fill="{it.color}"/>')
        return out

    @staticmethod
    def _drawable(v: np.ndarray | None, log: bool) -> np.ndarray:
        if v is None:
            return np.array([], dtype=bool)
        with np.errstate(invalid="ignore"):
            return np.isfinite(v) & ((v > 0) if log else True)

    def _legend(self, x: float, y: float) -> list[str]:
        out = []
        seen = set()
        row = 0
        for it in self.items:
            if not it.label or it.label in seen:
                continue
            seen.add(it.label)
            cy = y + 8 + 18 * row
            if it.kind == "band":
                out.append(f'<rect x="{x}" y="{cy - 6}" width="22" height="12" fill="{it.color}" '
                           f'fill-opacity="{max(it.opacity, 0.3)}"/>')
            elif it.kind == "markers":
                out.append(f'<circle cx="{x + 11}" cy="{cy}" r="3" fill="{it.color}"/>')
            else:
                dash = f' stroke-dasharray="{it.dash}"' if it.dash else ""
                out.append(f'<line x1="{x}" y1="{cy}" x2="{x + 22}" y2="{cy}" '
                           f'stroke="{it.color}" stroke-width="{max(it.width, 1.5)}"{dash}/>')
            out.append(f'<text x="{x + 28}" y="{cy + 4}" font-size="11">'
                       f'{escape(_clip(it.label, 26))}</text>')
            row += 1
        return out


def _arr(v) -> np.ndarray:
    return np.asarray(v, dtype=np.float64).ravel()


def _tf(v: np.ndarray, log: bool) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    if log:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log10(v)
    return v


def _runs(ok: np.ndarray) -> list[np.ndarray]:
    """Index arrays of consecutive true values."""
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return []
    return np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)


def _clip(text: str, n: int) -> str:
    return text if len(text) <= n else text[: n - 1] + "\u2026"


def _decade_label(e: int) -> str:
    if e == 0:
        return "1"
    if e == 1:
        return "10"
    sign = "\u2212" if e < 0 else ""
    return f'10<tspan dy="-6" font-size="9">{sign}{abs(e)}</tspan><tspan dy="6"></tspan>'


def _ticks(lo: float, hi: float, log: bool) -> list[tuple[float, str, bool]]:
    """(position in axis coordinates, label markup or "", is major) for one axis."""
    ticks: list[tuple[float, str, bool]] = []
    if log:
        span = hi - lo
        step = max(1, int(math.ceil(span / 8)))  # at most about 8 labelled decades
        for e in range(int(math.floor(lo)), int(math.ceil(hi)) + 1):
            if lo <= e <= hi:
                ticks.append((float(e), _decade_label(e) if e % step == 0 else "", True))
            for k in range(2, 10):
                p = e + math.log10(k)
                if lo <= p <= hi:
                    label = ""
                    if span < 1.2 and k in (2, 5):
                        label = _fmt(k * 10.0**e)
                    ticks.append((p, label, False))
        return ticks
    raw = (hi - lo) / 6
    mag = 10 ** math.floor(math.log10(raw))
    step = next(s * mag for s in (1, 2, 2.5, 5, 10) if s * mag >= raw)
    v = math.ceil(lo / step) * step
    while v <= hi + 1e-12 * step:
        ticks.append((v, _fmt(0.0 if abs(v) < step * 1e-9 else v), True))
        v += step
    return ticks


def _fmt(v: float) -> str:
    """Short tick label: 0.5, 12, 2.5e-05 -> written with a real minus sign."""
    text = f"{v:.3g}"
    if "e" in text:
        mant, exp = text.split("e")
        text = f"{mant}e{int(exp)}"
    return text.replace("-", "\u2212")
