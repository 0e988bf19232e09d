"""The fleet summary (:func:`imunoise.fleet.view.fleet_summary`) as one self-contained HTML page.

Plots are inline SVG on logarithmic value axes (decades labelled, as coefficients span
decades): per population and coefficient, every unit's pooled value with its 95 % interval,
outliers in red; per flagged unit (outlier, grown or disagreeing recordings), the coefficient
over time. No script and no external resource: the page can be mailed or archived.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

from imunoise.fleet.catalog import COEFFICIENTS

_W, _H, _PAD_L, _PAD_B, _PAD_T, _PAD_R = 340, 220, 62, 60, 14, 10
_RED, _BLUE = "#c62828", "#1f5fa8"
_SHOW_ALL_UNITS = 12
"""Up to this many unit x channel pairs, every history is drawn; beyond, the flagged ones."""

_CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:24px;color:#222;max-width:1100px}
h1{font-size:22px} h2{font-size:18px;margin-top:28px;border-bottom:1px solid #ddd}
h3{font-size:15px;margin:18px 0 4px} table{border-collapse:collapse;margin:8px 0}
td,th{border:1px solid #ddd;padding:3px 8px;text-align:left;font-variant-numeric:tabular-nums}
th{background:#f4f4f4} .bad{color:#c62828;font-weight:600} .ok{color:#2e7d32}
.marginal{color:#e65100} .note{color:#555;font-size:13px} svg{display:block}
.row{display:flex;flex-wrap:wrap;gap:8px} .empty{width:340px;height:220px;display:flex;
align-items:center;justify-content:center;color:#777;border:1px dashed #ccc;font-size:13px}
"""


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.4g}" if isinstance(v, float) else html.escape(str(v))


def _log_range(values: Sequence[float]) -> tuple[float, float]:
    good = [math.log10(v) for v in values if v is not None and v > 0 and math.isfinite(v)]
    if not good:
        return 0.0, 1.0
    lo, hi = math.floor(min(good) - 0.05), math.ceil(max(good) + 0.05)
    return float(lo), float(max(hi, lo + 1))


def _y_axis(lo: float, hi: float, label: str) -> list[str]:
    """Decade ticks labelled, minor ticks (2..9) unlabelled."""
    out = []
    span = _H - _PAD_T - _PAD_B
    for d in range(int(lo), int(hi) + 1):
        for k in range(1, 10):
            v = d + math.log10(k)
            if v > hi + 1e-9:
                break
            y = _PAD_T + span * (1 - (v - lo) / (hi - lo))
            if k == 1:
                out.append(f'<line x1="{_PAD_L - 6}" x2="{_W - _PAD_R}" y1="{y:.1f}" '
                           f'y2="{y:.1f}" stroke="#e6e6e6"/><text x="{_PAD_L - 8}" '
                           f'y="{y + 4:.1f}" text-anchor="end" font-size="11">1e{d}</text>')
            else:
                out.append(f'<line x1="{_PAD_L - 3}" x2="{_PAD_L}" y1="{y:.1f}" y2="{y:.1f}" '
                           'stroke="#999"/>')
    out.append(f'<text x="14" y="{_PAD_T + span / 2:.0f}" font-size="11" text-anchor="middle" '
               f'transform="rotate(-90 14 {_PAD_T + span / 2:.0f})">{html.escape(label)}</text>')
    return out


def _points_svg(labels: list[str], values: list[float | None], ci: list[Sequence | None],
                red: list[bool], y_label: str) -> str:
    """Points with 95 % bars on a log axis, one column per label."""
    lows = [c[0] for c in ci if c and c[0]]
    highs = [c[1] for c in ci if c and c[1]]
    lo, hi = _log_range([v for v in values if v] + lows + highs)
    span, n = _H - _PAD_T - _PAD_B, max(1, len(labels))
    step = (_W - _PAD_L - _PAD_R) / n

    def y(v: float) -> float:
        return _PAD_T + span * (1 - (math.log10(v) - lo) / (hi - lo))

    parts = [f'<svg width="{_W}" height="{_H}" role="img" aria-label="{html.escape(y_label)}">']
    parts += _y_axis(lo, hi, y_label)
    for i, (name, v, c, r) in enumerate(zip(labels, values, ci, red, strict=True)):
        x = _PAD_L + step * (i + 0.5)
        colour = _RED if r else _BLUE
        if c and c[0] and c[1] and c[0] > 0:
            parts.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{y(c[0]):.1f}" '
                         f'y2="{y(c[1]):.1f}" stroke="{colour}" stroke-width="1.5"/>')
        if v and v > 0:
            parts.append(f'<circle cx="{x:.1f}" cy="{y(v):.1f}" r="3.5" fill="{colour}"/>')
        if n <= 40:
            parts.append(f'<text x="{x:.1f}" y="{_H - _PAD_B + 14}" font-size="10" '
                         f'text-anchor="end" transform="rotate(-45 {x:.1f} '
                         f'{_H - _PAD_B + 14})">{html.escape(name)}</text>')
    parts.append("</svg>")
    return "".join(parts)


def _empty(coef: str, unit: str) -> str:
    return (f'<div class="empty">{coef} [{html.escape(unit)}]: not resolved in any '
            'recording</div>')


def _population_html(p: dict) -> str:
    out = [f'<h3>{html.escape(p["sensor_model"])} / {html.escape(p["channel"])} '
           f'({p["units"]} unit(s))</h3><div class="row">']
    for coef in COEFFICIENTS:
        d = p["coefficients"][coef]
        us = d["units"]
        if not any(u["value"] for u in us):
            out.append(_empty(coef, d["si_unit"]))
            continue
        out.append(_points_svg([u["unit"] for u in us], [u["value"] for u in us],
                               [u["ci95"] for u in us], [u["outlier"] for u in us],
                               f'{coef} [{d["si_unit"]}]'))
    return "".join(out) + "</div>"


def _history_html(u: dict) -> str:
    out = [f'<h3>unit {html.escape(u["unit"])}, {html.escape(u["channel"])}</h3>'
           '<div class="row">']
    for coef in COEFFICIENTS:
        d = u["coefficients"][coef]
        h = d["history"]
        pooled = d["pooled"]
        note = ""
        if pooled:
            note = (f'pooled {_fmt(pooled["value"])} [{_fmt(pooled["ci95"][0])}, '
                    f'{_fmt(pooled["ci95"][1])}] {html.escape(d["si_unit"])}; recordings '
                    + ('<span class="ok">agree</span>' if pooled["agree"] else
                       '<span class="bad">disagree</span>' if pooled["agree"] is False else
                       "single") + f' (p = {_fmt(pooled["p_value"])})')
        if d["grew"]:
            note += ' <span class="bad">grew beyond its intervals</span>'
        if not any(e["value"] for e in h):
            out.append(_empty(coef, d["si_unit"]))
            continue
        out.append(f'<div><p class="note" style="width:{_W}px">{coef}: {note}</p>')
        out.append(_points_svg([(e["start_time"] or "?")[:10] for e in h],
                               [e["value"] for e in h], [e["ci95"] for e in h],
                               [False] * len(h), f'{coef} [{d["si_unit"]}]') + "</div>")
    return "".join(out) + "</div>"


def _table(head: list[str], rows: list[list[str]]) -> str:
    return ("<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
            + "</table>")


def _verdict(v: str) -> str:
    cls = {"fail": "bad", "pass": "ok", "marginal": "marginal"}.get(v, "")
    return f'<span class="{cls}">{v}</span>'


def render_fleet(doc: dict[str, Any]) -> str:
    """The page of a fleet document."""
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>imunoise fleet"
             f"</title><style>{_CSS}</style></head><body><h1>Fleet: "
             f"{html.escape(doc['catalog'])}</h1>",
             f"<p>{doc['files']} recording(s): {doc['files_ok']} analysed, "
             f"<span class='{'bad' if doc['files_failed'] else ''}'>{doc['files_failed']} "
             f"failed</span>; {len(doc['populations'])} population(s) (sensor model x "
             f"channel).</p>"]
    parts.append("<h2>Outliers</h2><p class='note'>" + html.escape(doc["outlier_test"])
                 + "</p>")
    parts.append(_table(["sensor model", "channel", "coefficient", "unit", "value", "M"],
                        [[html.escape(o["sensor_model"]), html.escape(o["channel"]),
                          o["coefficient"], f"<b>{html.escape(o['unit'])}</b>",
                          _fmt(o["value"]), _fmt(o["m_score"])] for o in doc["outliers"]])
                 if doc["outliers"] else "<p>No unit is an outlier.</p>")
    if doc["limits"]:
        bad = [r for r in doc["limits"] if r["verdict"] != "pass"]
        parts.append(f"<h2>Limits</h2><p>{len(doc['limits']) - len(bad)} of "
                     f"{len(doc['limits'])} checks pass.</p>")
        parts.append(_table(["file", "unit", "channel", "coef.", "value", "95 % interval",
                             "limit", "verdict"],
                            [[html.escape(r["file"]), html.escape(r["unit"]), r["channel"],
                              r["coefficient"], _fmt(r["value"]),
                              f"{_fmt(r['ci95'][0])} - {_fmt(r['ci95'][1])}",
                              f"max {_fmt(r['max'])}" if r["max"] is not None
                              else f"min {_fmt(r['min'])}", _verdict(r["verdict"])]
                             for r in bad]) if bad else "")
    parts.append("<h2>Populations</h2><p class='note'>Each point: a unit's recordings pooled, "
                 "with the 95 % interval; red: outlier.</p>")
    parts += [_population_html(p) for p in doc["populations"]]
    flagged = {(o["unit"], o["channel"]) for o in doc["outliers"] + doc["grew"]
               + doc["disagree"]}
    few = len(doc["units"]) <= _SHOW_ALL_UNITS
    shown = [u for u in doc["units"] if few or (u["unit"], u["channel"]) in flagged]
    parts.append("<h2>Units over time</h2><p class='note'>" + html.escape(doc["agreement_test"])
                 + (". Every unit." if few else
                    ". Shown: units flagged as outliers, grown or disagreeing.") + "</p>")
    parts += [_history_html(u) for u in shown] or ["<p>No unit is flagged.</p>"]
    parts.append("<h2>Pooled values of every unit</h2>")
    parts.append(_table(
        ["unit", "model", "channel", "rec."] + [f"{c} pooled (95 %)" for c in COEFFICIENTS]
        + ["recordings agree"],
        [[html.escape(u["unit"]), html.escape(u["sensor_model"]), u["channel"],
          str(u["recordings"])]
         + [(f"{_fmt(d['pooled']['value'])} [{_fmt(d['pooled']['ci95'][0])}, "
             f"{_fmt(d['pooled']['ci95'][1])}] {html.escape(d['si_unit'])}")
            if d["pooled"] else "not resolved" for d in u["coefficients"].values()]
         + [", ".join(f"{c}: {'yes' if d['pooled']['agree'] else 'no'}"
                      for c, d in u["coefficients"].items()
                      if d["pooled"] and d["pooled"]["agree"] is not None) or "-"]
         for u in doc["units"]]))
    if doc["failed"]:
        parts.append("<h2>Failed recordings</h2>")
        parts.append(_table(["file", "error"], [[html.escape(f["file"]),
                                                  html.escape(f["error"] or "")]
                                                 for f in doc["failed"]]))
    parts.append("</body></html>")
    return "".join(parts)
