"""The morning-after HTML report: one self-contained file with inline SVG plots.

Input is the ``analyze --json`` document (docs/json.md keys per channel) extended with:

- ``discrete_model`` per channel: :meth:`imunoise.analysis.discrete.DiscreteModel.to_dict`;
- ``discrete_check`` per channel: ``{"tau_s", "adev", "inside", "total"}``, the Allan deviation
  of a simulation of the discrete model and how many of its points lie inside the measured band;
- ``suggestions`` per channel (``diagnose`` keys), optional;
- ``terms_adev`` per channel: ``{term: [adev on allan.tau_s]}``, each fitted term's own curve;
- ``model_psd`` per channel: ``{"f_hz", "psd"}``, optional;
- ``record`` at the top level: the record's facts (device, rate, duration, gaps, drops,
  temperature range, warnings);
- ``coherence`` at the top level (``analyze``'s, optional): the coherence between channels and
  the lines classified as common or own (docs/environment.md);
- ``own`` per channel (``--subtract-common``, optional): the channel's analysis after the
  common part is removed.

Nothing is fetched from the network: styles are inline, plots are SVG, no scripts.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Mapping, Sequence
from html import escape

import numpy as np

from imunoise.core.units import conventional, si_unit
from imunoise.export.svg_plot import PALETTE, Plot
from imunoise.version import __version__

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;
 margin:0 auto;max-width:1100px;padding:16px 24px;color:#1d2330;background:#fff;line-height:1.4}
h1{font-size:1.6em;margin:.2em 0}h2{border-bottom:2px solid #1f4e9c;padding-bottom:3px;
 margin-top:2em}h3{margin:1.2em 0 .4em}
table{border-collapse:collapse;margin:.4em 0 1em;font-size:.92em}
th,td{border:1px solid #c8ccd4;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#eef1f6}td.num{text-align:right;font-variant-numeric:tabular-nums;
 white-space:nowrap}
.ok{color:#1e7b3a;font-weight:600}.bad{color:#b22222;font-weight:600}
.muted{color:#666;font-size:.9em}.plots svg{display:block;margin:.4em 0;max-width:100%;
 height:auto}.warn{background:#fff4e0;border-left:4px solid #e6a23c;padding:4px 10px}
nav a{margin-right:1em}
"""

_PARAM_ORDER = ("N", "Q", "B", "K", "R", "sigma", "T", "A", "f", "coef")


def _conventional(param: str, kind: str) -> tuple[str, float] | None:
    """Conventional unit label and SI-to-conventional factor, None for an unknown parameter."""
    try:
        label, factor = conventional(param, kind)
    except ValueError:
        return None
    return str(label), float(factor)


def _si_unit(param: str, kind: str) -> str:
    """SI unit of a term parameter for a gyro or accelerometer channel."""
    try:
        return si_unit(param, kind)
    except ValueError:
        return ""


def _num(v: float | None, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "\u2013"
    v = float(v)
    if v == 0:
        return "0"
    if 1e-3 <= abs(v) < 1e5:
        return f"{v:.{max(digits, int(math.log10(abs(v))) + 1)}g}"
    mant, exp = f"{v:.{digits - 1}e}".split("e")
    return f"{mant}\u00d710<sup>{int(exp)}</sup>"


def _interval(ci: Sequence[float] | None, factor: float = 1.0) -> str:
    if not ci or len(ci) != 2 or ci[0] is None or ci[1] is None:
        return "\u2013"
    return f"[{_num(ci[0] * factor)}, {_num(ci[1] * factor)}]"


def _value_cell(resolved: bool, v: float, ci: Sequence[float] | None, unit: str,
                factor: float = 1.0) -> str:
    """A parameter's value and its interval below, or (not ``resolved``: the model entry's
    ``unresolved`` names it) "not resolved" and the upper bound."""
    if not resolved:
        hi = ci[1] if ci and ci[1] is not None else None
        bound = "" if hi is None else f" (95 % upper bound {_num(hi * factor)} {unit})"
        return f'<td class="num">not resolved<br><span class="muted">{bound}</span></td>'
    return (f'<td class="num">{_num(v * factor)} {unit}<br>'
            f'<span class="muted">{_interval(ci, factor)}</span></td>')


def _kind(channel: str) -> str:
    return "gyro" if channel.split(":")[-1].startswith("gyro") else "accel"


def _arr(d: Mapping | None, key: str) -> np.ndarray:
    if not d or d.get(key) is None:
        return np.array([])
    return np.asarray(d[key], dtype=np.float64)


def render_report(doc: Mapping, title: str | None = None,
                  generated: _dt.datetime | None = None) -> str:
    """The complete HTML report for an extended ``analyze`` document."""
    channels: Mapping[str, Mapping] = doc.get("channels", {})
    src = str(doc.get("file", ""))
    title = title or f"imunoise noise report: {src}"
    when = (generated or _dt.datetime.now(_dt.UTC)).strftime("%Y-%m-%d %H:%M UTC")
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             f"<title>{escape(title)}</title><style>{_CSS}</style></head><body>",
             f"<h1>{escape(title)}</h1>",
             f'<p class="muted">Generated {when} by imunoise {escape(__version__)}. '
             "Values in SI units with conventional units beside them; intervals are 95 %.</p>"]
    if channels:
        links = [f'<a href="#ch-{escape(n)}">{escape(n)}</a>' for n in channels]
        if (doc.get("coherence") or {}).get("pairs"):
            links.append('<a href="#coherence">coherence</a>')
        parts.append("<nav>" + "".join(links) + "</nav>")
    parts.append(_record_section(doc.get("record") or {}, src))
    parts.append(_summary_section(channels))
    for name, ch in channels.items():
        parts.append(_channel_section(name, ch))
    parts.append(_coherence_section(doc.get("coherence") or {}))
    parts.append(_method_section())
    parts.append("</body></html>")
    return "\n".join(parts)


def _coherence_section(co: Mapping) -> str:
    """The cross-channel view: the coherence matrix (highest coherence of each pair), the
    pairs that pass the zero-coherence test drawn on log-frequency axes, and every line
    classified common or own."""
    if not co or not co.get("pairs"):
        return ""
    chans = list(co.get("channels", []))
    pairs = [tuple(p) for p in co["pairs"]]
    f = np.asarray(co["f_hz"], dtype=np.float64)
    msc = np.asarray(co["msc"], dtype=np.float64)
    fam = np.asarray(co.get("threshold_family", co["threshold"]), dtype=np.float64)
    peak = np.nanmax(msc, axis=1) if msc.size else np.zeros(len(pairs))
    at = {p: (float(peak[k]), float(f[int(np.nanargmax(msc[k]))]) if msc.size else 0.0)
          for k, p in enumerate(pairs)}
    head = "<tr><th></th>" + "".join(f"<th>{escape(c)}</th>" for c in chans) + "</tr>"
    rows = []
    for a in chans:
        cells = []
        for b in chans:
            v = at.get((a, b)) or at.get((b, a))
            if a == b or v is None:
                cells.append("<td></td>")
                continue
            shade = int(round(255 * (1 - v[0])))
            cells.append(f'<td style="background:rgb(255,{shade},{shade})" title="highest '
                         f'coherence {v[0]:.3f} at {v[1]:.3g} Hz">{v[0]:.2f}<br>'
                         f'<span class="muted">{v[1]:.3g} Hz</span></td>')
        rows.append(f"<tr><th>{escape(a)}</th>{''.join(cells)}</tr>")
    out = ['<h2 id="coherence">Coherence between channels</h2>',
           '<p class="muted">Magnitude-squared coherence (Welch, Hann, 50 % overlap, '
           f'{co.get("nperseg")} samples per segment): the share of one channel\'s power at a '
           "frequency that the other explains. Matrix: each pair's highest coherence and where. "
           "Plots: pairs that pass the zero-coherence test (family-wise 5 %) somewhere, with "
           "the exact 95 % interval and the threshold.</p>",
           f"<table class=\"matrix\">{head}{''.join(rows)}</table>"]
    lo = np.asarray(co.get("ci", {}).get("low", msc), dtype=np.float64)
    hi = np.asarray(co.get("ci", {}).get("high", msc), dtype=np.float64)
    shown = [k for k in np.argsort(-peak) if np.any(msc[k] > fam)][:_MAX_PAIR_PLOTS]
    for k in shown:
        a, b = pairs[k]
        p = Plot(f"coherence {a} - {b}", "frequency (Hz)", "magnitude-squared coherence",
                 x_log=True, y_log=False, height=300)
        p.band(f, lo[k], hi[k], label="95 % interval")
        p.line(f, msc[k], label="coherence")
        p.line(f, fam, label="zero-coherence threshold (5 %, family)", color="#555555")
        out.append(f'<div class="plot">{p.svg()}</div>')
    cls = co.get("classification") or []
    if cls:
        body = "".join(
            f"<tr><td>{escape(str(c['channel']))}</td><td>{escape(str(c['term']))}</td>"
            f"<td>{_num(c['f_hz'], 4)} Hz</td><td><strong>{escape(str(c['origin']))}</strong>"
            f"</td><td>{escape(', '.join(c.get('common_with') or []))}</td>"
            f"<td>{escape(str(c.get('why', '')))}</td></tr>" for c in cls)
        out.append("<h3>Lines and resonances: environment or sensor</h3><table><tr>"
                   "<th>channel</th><th>term</th><th>frequency</th><th>origin</th>"
                   f"<th>common with</th><th>why</th></tr>{body}</table>")
    shapes = co.get("shared_shapes") or []
    if shapes:
        out.append("<h3>One spectral shape, no common signal: the chain's filter</h3>")
        out.extend(f"<p>{escape(str(s.get('text', '')))}</p>" for s in shapes)
    return "\n".join(out)


_MAX_PAIR_PLOTS = 6
"""Coherent pairs drawn (the highest first); the matrix shows every pair."""


def _record_section(rec: Mapping, src: str) -> str:
    rows = [("file", escape(src))]
    labels = [
        ("device", "device", None), ("source", "source", None),
        ("fs_hz", "sample rate", "Hz"), ("duration_s", "sampled duration", "s"),
        ("span_s", "time span (first to last sample)", "s"), ("n_samples", "samples", None),
        ("segments", "gap-free segments", None), ("gaps", "gaps", None),
        ("gap_time_s", "time in gaps", "s"), ("dropped", "samples dropped", None),
    ]
    for key, label, unit in labels:
        if key in rec and rec[key] is not None:
            v = rec[key]
            text = (_num(v, 6) if isinstance(v, float) else escape(str(v))) + (
                f" {unit}" if unit else "")
            if key == "duration_s" and isinstance(v, int | float):
                text += f" ({v / 3600:.2f} h)"
            rows.append((label, text))
    tr = rec.get("temperature_range_degC")
    if tr:
        rows.append(("temperature range", f"{_num(tr[0], 4)} to {_num(tr[1], 4)} \u00b0C "
                     f"(spread {_num(tr[1] - tr[0], 3)} \u00b0C)"))
    elif "temperature_range_degC" in rec:
        rows.append(("temperature range", "not recorded"))
    body = "".join(f"<tr><th>{a}</th><td>{b}</td></tr>" for a, b in rows)
    meta = rec.get("metadata") or {}
    if meta:
        mrows = "".join(f"<tr><th>{escape(str(k))}</th><td>{escape(str(v))}</td></tr>"
                        for k, v in meta.items())
        body += (f'<tr><th>metadata</th><td><details><summary>{len(meta)} entries</summary>'
                 f"<table>{mrows}</table></details></td></tr>")
    warn = "".join(f'<p class="warn">{escape(str(w))}</p>' for w in rec.get("warnings") or [])
    return f'<h2 id="record">Record</h2><table>{body}</table>{warn}'


def _param(ch: Mapping, term: str, param: str) -> tuple[float | None, list | None]:
    for t in ch.get("model") or []:
        if t.get("term") == term and param in (t.get("params") or {}):
            return float(t["params"][param]), (t.get("ci95") or {}).get(param)
    return None, None


def _summary_section(channels: Mapping[str, Mapping]) -> str:
    head = ("<tr><th>channel</th><th>N (white)</th><th>B (bias instability)</th>"
            "<th>K (rate random walk)</th><th>Allan \u03c7\u00b2/dof</th>"
            "<th>PSD deviance/bin</th><th>model fits?</th></tr>")
    rows = []
    for name, ch in channels.items():
        cells = [f'<td><a href="#ch-{escape(name)}">{escape(name)}</a></td>']
        for term, p in (("white", "N"), ("bias_instability", "B"), ("random_walk", "K")):
            v, _ = _param(ch, term, p)
            conv = _conventional(p, _kind(name))
            if v is None:
                cells.append('<td class="num">\u2013</td>')
            elif conv:
                cells.append(f'<td class="num">{_num(v * conv[1], 3)} {escape(conv[0])}</td>')
            else:
                cells.append(f'<td class="num">{_num(v, 3)} '
                             f'{escape(_si_unit(p, _kind(name)))}</td>')
        err = ch.get("error") or {}
        chi2 = err.get("chi2_per_dof")
        cells.append(f'<td class="num">{_num(chi2, 3)}</td>')
        cells.append(f'<td class="num">{_num((err.get("psd") or {}).get("deviance_per_bin"), 3)}'
                     "</td>")
        fails = ch.get("failures") or []
        cells.append('<td class="ok">yes</td>' if chi2 is not None and not fails else
                     f'<td class="bad">{len(fails)} failing range(s)</td>' if fails else
                     "<td>\u2013</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f'<h2 id="summary">Summary</h2><table>{head}{"".join(rows)}</table>'


def _channel_section(name: str, ch: Mapping) -> str:
    units = str(ch.get("units", ""))
    kind = _kind(name)
    out = [f'<h2 id="ch-{escape(name)}">{escape(name)} <span class="muted">({escape(units)}, '
           f'{_num(ch.get("fs_hz"), 6)} Hz, {ch.get("n_samples", "?")} samples)</span></h2>']
    out.extend(f'<p class="warn">{escape(str(w))}</p>' for w in ch.get("warnings") or [])
    out.append("<h3>Fitted model</h3>")
    out.append(_coefficient_table(ch, kind))
    out.append(_error_block(ch))
    out.append('<div class="plots">')
    out.append(_allan_plot(name, ch, units))
    out.append(_z_plot(name, ch))
    out.append(_psd_plot(name, ch, units))
    out.append("</div>")
    out.append(_discrete_block(ch, units, kind))
    out.append(_diagnosis_block(ch))
    out.append(_own_block(name, ch, units, kind))
    return "\n".join(out)


def _own_block(name: str, ch: Mapping, units: str, kind: str) -> str:
    """The channel's own noise (``--subtract-common``) beside the raw: the Allan deviations
    together, the own model and white level, the subtraction's error."""
    own = ch.get("own")
    if not own:
        return ""
    sub = own.get("subtraction") or {}
    err = sub.get("error") or {}
    refs = ", ".join(sub.get("references") or [])
    bands = "; ".join(f"{_num(a, 3)}–{_num(b, 3)} Hz" for a, b in
                      sub.get("bands_subtracted_hz") or [])
    out = ["<h3>Own noise: the other channels' coherent part removed</h3>",
           f"<p>References: {escape(refs)}. Removed where the multiple coherence passes the "
           f"zero-coherence test ({escape(bands) or 'nowhere'}): "
           f"{_num(100 * err.get('removed_share', 0.0), 3)} % of the variance. Error of the "
           f"subtraction: at most {_num(100 * err.get('leak_share', 0.0), 3)} % of the "
           "residual is the references' own noise passed in; the residual PSD is low by the "
           f"factor {_num(err.get('bias_factor'), 4)} where subtracted.</p>"]
    wl = own.get("white_level") or {}
    if wl.get("N") is not None:
        lo, hi = wl.get("ci") or (None, None)
        out.append(f"<p>Own white level read at τ = {_num(wl.get('tau_s'), 3)} s: "
                   f"<b>{_num(wl['N'], 4)}</b> [{_num(lo, 4)}, {_num(hi, 4)}] "
                   f"{escape(units)}/√Hz (the interval's lower end allows for the "
                   "references' noise).</p>")
    out.append(_coefficient_table(own, kind))
    out.append(_error_block(own))
    raw_a, own_a = ch.get("allan") or {}, own.get("allan") or {}
    if raw_a.get("tau_s") and own_a.get("tau_s"):
        p = Plot(f"{name}: raw and own Allan deviation", "averaging time \u03c4 (s)",
                 f"Allan deviation ({units})")
        p.band(raw_a["tau_s"], raw_a["ci_low"], raw_a["ci_high"], label="raw 95 %")
        p.line(raw_a["tau_s"], raw_a["adev"], label="raw")
        p.band(own_a["tau_s"], own_a["ci_low"], own_a["ci_high"], label="own 95 %")
        p.line(own_a["tau_s"], own_a["adev"], label="own (common part removed)")
        out.append(f'<div class="plots">{p.svg()}</div>')
    if own.get("suggestions") is not None:
        out.append(_diagnosis_block(own).replace("<h3>Diagnosis</h3>",
                                                 "<h3>Diagnosis of the own noise</h3>", 1))
    return "\n".join(out)


def _coefficient_table(ch: Mapping, kind: str) -> str:
    model = ch.get("model") or []
    if not model:
        return '<p class="muted">No model was fitted.</p>'
    head = ("<tr><th>term</th><th>parameter</th><th>SI value<br><span class=\"muted\">95 % "
            "interval</span></th><th>conventional value<br><span class=\"muted\">95 % "
            "interval</span></th></tr>")
    rows = []
    for t in model:
        params = t.get("params") or {}
        ci95 = t.get("ci95") or {}
        keys = sorted(params, key=lambda p: _PARAM_ORDER.index(p) if p in _PARAM_ORDER else 99)
        for p in keys:
            v = float(params[p])
            si = escape(_si_unit(p, kind))
            conv = _conventional(p, kind)
            resolved = p not in (t.get("unresolved") or [])
            conv_cell = ("<td>\u2013</td>" if conv is None else
                         _value_cell(resolved, v, ci95.get(p), escape(conv[0]), conv[1]))
            rows.append(f"<tr><td>{escape(str(t.get('term')))}</td><td>{escape(p)}</td>"
                        f"{_value_cell(resolved, v, ci95.get(p), si)}{conv_cell}</tr>")
    return f"<table>{head}{''.join(rows)}</table>"


def _part_cells(err: Mapping) -> list[str]:
    """The error's parts beside the Allan one, as table cells: the PSD deviance per bin (with
    the share of bins outside their 95 % interval), the hold-out chi2/dof (with the named
    changes fitted, where any) and the time-domain statistic with its p-value; a part not
    computed says why."""
    def missing(part: Mapping | None) -> str:
        why = (part or {}).get("reason") or "not computed"
        return f'<td class="muted">{escape(str(why))}</td>'

    psd = err.get("psd") or {}
    ho = err.get("holdout") or {}
    td = err.get("time_domain") or {}
    cells = []
    if psd.get("deviance_per_bin") is None:
        cells.append(missing(psd))
    else:
        out = psd.get("outside_95")
        share = "" if out is None else (f" ({_num(100.0 * out, 2)} % of {psd.get('bins')} "
                                        "bins outside 95 %)")
        cells.append(f'<td class="num">{_num(psd["deviance_per_bin"], 3)}{share}</td>')
    if ho.get("chi2_per_dof") is None:
        cells.append(missing(ho))
    else:
        free = (ho.get("changes_free") or {}).get("chi2_per_dof")
        loose = "" if free is None else f" ({_num(free, 3)} with the changes named fitted)"
        cells.append(f'<td class="num">{_num(ho["chi2_per_dof"], 3)}{loose}</td>')
    if td.get("statistic") is None:
        cells.append(missing(td))
    else:
        cells.append(f'<td class="num">max |z| {_num(td["statistic"], 3)} '
                     f'(p {_num(td.get("p"), 2)})</td>')
    return cells


def _psd_misses(psd: Mapping) -> str:
    """Where the measured spectrum leaves the model's band, the misses that make the PSD
    part large first told, as a list."""
    from imunoise.analysis.model_error import psd_miss_lines

    items = "".join(f"<li>{escape(m)}</li>" for m in psd_miss_lines(dict(psd)))
    return f"<p>Where the spectrum misses the model:</p><ul>{items}</ul>" if items else ""


def _holdout_findings(ho: Mapping) -> str:
    """The parameters that changed between the halves, and a difference of the halves taken
    together, as a list (findings about the sensor, not failures of the model)."""
    from imunoise.analysis.model_error import holdout_findings

    items = "".join(f"<li>{escape(f)}</li>" for f in holdout_findings(dict(ho)))
    return f"<p>Findings of the hold-out part:</p><ul>{items}</ul>" if items else ""


def _error_block(ch: Mapping) -> str:
    err = ch.get("error") or {}
    if not err:
        return ""
    fails = ch.get("failures") or []
    text = (f"<p>Misfit \u03c7\u00b2/dof = <b>{_num(err.get('chi2_per_dof'), 3)}</b> "
            f"(about 1 when the model explains the measurement), largest |z| = "
            f"{_num(err.get('max_abs_z'), 3)}.</p>")
    text += ("<table><tr><th>Allan \u03c7\u00b2/dof</th><th>PSD deviance/bin</th>"
             "<th>hold-out \u03c7\u00b2/dof</th><th>time domain</th></tr><tr>"
             f'<td class="num">{_num(err.get("chi2_per_dof"), 3)}</td>'
             + "".join(_part_cells(err)) + "</tr></table>"
             '<p class="muted">Each part is about 1 when the model describes the sensor: the '
             "Allan curve, the measured spectrum against the model's expected one, the model "
             "fitted on one half of the record predicting the other half; the time-domain "
             "part tests for a bias step or warm-up under the model.</p>")
    text += _psd_misses(err.get("psd") or {})
    text += _holdout_findings(err.get("holdout") or {})
    if not fails:
        return text + ('<p class="ok">The measurement stays inside the model\'s band at every '
                       "\u03c4.</p>")
    def span(lo: float, hi: float) -> str:
        if lo == hi:
            return f"\u03c4 = {_num(lo, 3)} s"
        return f"\u03c4 = {_num(lo, 3)} to {_num(hi, 3)} s"

    items = "".join(
        f"<li>{span(*f['tau_s'])}: {escape(str(f.get('direction', '')))}, |z| up to "
        f"{_num(f.get('max_abs_z'), 3)}</li>" for f in fails)
    return text + f'<p class="bad">Where the model fails:</p><ul>{items}</ul>'


def _allan_plot(name: str, ch: Mapping, units: str) -> str:
    al = ch.get("allan") or {}
    tau = _arr(al, "tau_s")
    p = Plot(f"{name}: overlapping Allan deviation", "averaging time \u03c4 (s)",
             f"Allan deviation ({units})")
    if tau.size:
        p.band(tau, _arr(al, "ci_low"), _arr(al, "ci_high"), "measured, 95 % band",
               color=PALETTE[0])
        p.line(tau, _arr(al, "adev"), "measured", color=PALETTE[0], width=1.2)
        p.markers(tau, _arr(al, "adev"), None, color=PALETTE[0])
        mod = _arr(al, "model_adev")
        if mod.size == tau.size:
            p.line(tau, mod, "fitted model", color=PALETTE[1], width=2.2)
        for i, (term, dev) in enumerate((ch.get("terms_adev") or {}).items()):
            d = np.asarray(dev, dtype=np.float64)
            if d.size == tau.size:
                p.line(tau, d, f"term: {term}", color=PALETTE[(i + 2) % len(PALETTE)],
                       width=1.2, dash="5 3", autoscale=False)
        chk = ch.get("discrete_check") or {}
        st = _arr(chk, "tau_s")
        if st.size:
            p.line(st, _arr(chk, "adev"), "simulated discrete model", color="#000000",
                   width=1.2, dash="1 3")
        ob = (ch.get("discrete_model") or {}).get("overbound") or {}
        ot = _arr(ob, "tau_s")
        if ot.size:
            p.line(ot, _arr(ob, "model_adev"), "over-bounding model (filter-safe)",
                   color="#d62728", width=1.6, dash="8 3")
    return p.svg()


def _z_plot(name: str, ch: Mapping) -> str:
    al = ch.get("allan") or {}
    tau, z = _arr(al, "tau_s"), _arr(al, "z")
    p = Plot(f"{name}: standardised residuals z", "averaging time \u03c4 (s)",
             "z (measured \u2212 model) / \u03c3", y_log=False, height=240)
    if z.size and z.size == tau.size:
        p.hline(0.0, color="#333333", dash=None)
        p.hline(2.0, "|z| = 2", color="#999999")
        p.hline(-2.0, color="#999999")
        p.markers(tau, z, "z per \u03c4", color=PALETTE[1])
    return p.svg()


def _psd_plot(name: str, ch: Mapping, units: str) -> str:
    psd = ch.get("psd") or {}
    f = _arr(psd, "f_hz")
    p = Plot(f"{name}: power spectral density (one-sided)", "frequency (Hz)",
             f"PSD (({units})\u00b2/Hz)")
    if f.size:
        p.band(f, _arr(psd, "ci_low"), _arr(psd, "ci_high"), "measured, 95 % band",
               color=PALETTE[0])
        p.line(f, _arr(psd, "psd"), "measured", color=PALETTE[0], width=1.0)
        mp = ch.get("model_psd") or {}
        if _arr(mp, "f_hz").size:
            p.line(_arr(mp, "f_hz"), _arr(mp, "psd"), "fitted model", color=PALETTE[1],
                   width=2.2)
    return p.svg()


def _discrete_block(ch: Mapping, units: str, kind: str) -> str:
    dm = ch.get("discrete_model")
    if not dm:
        return ""
    rows = [
        ("sample period dt", f"{_num(dm['dt_s'])} s"),
        ("white measurement noise \u03c3<sub>d</sub> = N\u221afs",
         f"{_num(dm['white_sigma'])} {escape(units)}"),
        ("quantization: angle error std Q (sample = \u0394e/dt)",
         f"{_num(dm['quantization_sigma'])} {escape(_si_unit('Q', kind))}"),
        ("random-walk bias step K\u221adt", f"{_num(dm['random_walk_step'])} {escape(units)}"),
    ]
    if dm.get("ramp_rate"):
        rows.append(("rate ramp R", f"{_num(dm['ramp_rate'])} {escape(units)}/s"))
    for s in dm.get("sinusoids") or []:
        rows.append(("sinusoid A, f", f"{_num(s['A'])} {escape(units)}, {_num(s['f_hz'])} Hz"))
    if dm.get("temperature_coef"):
        rows.append(("temperature coefficient",
                     f"{_num(dm['temperature_coef'])} {escape(units)}/\u00b0C"))
    table = "".join(f"<tr><th>{a}</th><td class=\"num\">{b}</td></tr>" for a, b in rows)
    out = ["<h3>Discrete-time model for a filter</h3>",
           "<p>At the sample period: y<sub>k</sub> = v<sub>k</sub> + (e<sub>k</sub> \u2212 "
           "e<sub>k\u22121</sub>)/dt + b<sub>k</sub> + \u03a3<sub>j</sub> x<sub>j,k</sub>, with "
           "b<sub>k+1</sub> = b<sub>k</sub> + w<sub>k</sub> and x<sub>j,k+1</sub> = "
           "a<sub>j</sub> x<sub>j,k</sub> + u<sub>j,k</sub>.</p>", f"<table>{table}</table>"]
    markov = dm.get("markov") or []
    if markov:
        head = ("<tr><th>state</th><th>from term</th><th>T (s)</th><th>a<sub>d</sub> = "
                "exp(\u2212dt/T)</th><th>driving std \u03c3\u221a(1\u2212a<sub>d</sub>\u00b2)"
                f" ({escape(units)})</th><th>stationary std ({escape(units)})</th></tr>")
        body = "".join(
            f"<tr><td>x<sub>{i + 1}</sub></td><td>{escape(s['term'])}</td>"
            f'<td class="num">{_num(s["T_s"])}</td><td class="num">{s["a_d"]:.9f}</td>'
            f'<td class="num">{_num(s["driving_sigma"])}</td>'
            f'<td class="num">{_num(s["sigma"])}</td></tr>' for i, s in enumerate(markov))
        out.append(f"<table>{head}{body}</table>")
    fl = dm.get("bias_instability_approximation")
    if fl and not fl.get("states_per_decade"):
        out.append(f"<p>Bias instability B = {_num(fl['B'])} {escape(units)} is negligible here "
                   "(below 10<sup>\u22124</sup> of the model's Allan variance at every \u03c4): "
                   "it needs no state.</p>")
    elif fl:
        out.append(f"<p>Bias instability B = {_num(fl['B'])} {escape(units)} has no finite "
                   f"state model: it is approximated by the Markov states above (correlation "
                   f"times log-spaced, {_num(fl['states_per_decade'], 2)} per decade) fitted over "
                   f"\u03c4 = {_num(fl['tau_range_s'][0], 3)} to {_num(fl['tau_range_s'][1], 3)} s;"
                   f" the whole model's Allan variance is reproduced within "
                   f"{100 * fl['max_rel_avar_error']:.2g} %.</p>")
    ob = (ch.get("discrete_model") or {}).get("overbound") or {}
    if ob.get("tau_s"):
        states = ", ".join([f"white N = {_num(ob['N'])}", f"random walk K = {_num(ob['K'])}"]
                           + [f"Markov σ = {_num(m['sigma'])}, T = {_num(m['T_s'], 3)} s"
                              for m in ob.get("markov", [])])
        out.append(f"<p>Over-bounding model for a Kalman filter (dashed red in the Allan plot): "
                   f"{escape(states)}. Its Allan deviation lies on or above the measured upper "
                   f"95 % bound at every τ, by {100 * ob['median_excess']:.2g} % (median) "
                   f"and at most {100 * ob['max_excess']:.2g} %; filter-ready values in "
                   "<code>discrete_model.overbound.discrete</code> of the JSON.</p>")
    chk = ch.get("discrete_check") or {}
    if chk.get("total"):
        inside, total = int(chk["inside"]), int(chk["total"])
        cls = "ok" if inside >= 0.8 * total else "bad"
        text = (f"Check: a simulation of this discrete model ({chk.get('n_samples', '?')} "
                f"samples, dotted black curve in the Allan plot) agrees with the measurement at "
                f"{inside} of {total} averaging times (difference within the combined 95 % "
                "interval of the two estimates).")
        if chk.get("exact_total"):
            text += (f" The discrete model's exact Allan deviation lies inside the measured "
                     f"95 % band at {chk['exact_inside']} of {chk['exact_total']}.")
        out.append(f'<p class="{cls}">{text}</p>')
    return "\n".join(out)


def _diagnosis_block(ch: Mapping) -> str:
    sugg = ch.get("suggestions")
    if sugg is None:
        return ""
    if not sugg:
        return "<h3>Diagnosis</h3><p>No candidate term could be tried.</p>"
    fitted = (ch.get("error") or {}).get("chi2_per_dof")
    head = ("<tr><th>change</th><th>parameters</th><th>\u03c7\u00b2/dof before \u2192 after"
            "</th><th>significant</th><th>why</th></tr>")

    def row(s: Mapping) -> str:
        unresolved = s.get("unresolved") or []
        params = ", ".join(f"{escape(k)} not resolved" if k in unresolved else
                           f"{escape(k)} = {_num(v, 3)}"
                           for k, v in (s.get("params") or {}).items())
        sig = s.get("significant")
        verb = str(s.get("action") or "add")
        name = str(s.get("label") or s.get("term"))
        return (f"<tr><td>{escape(verb)} {escape(name)}</td><td>{params}</td>"
                f'<td class="num">{_num(s.get("chi2_per_dof_before", fitted), 3)} \u2192 '
                f"{_num(s.get('chi2_per_dof_after'), 3)}</td>"
                f'<td class="{"ok" if sig else "muted"}">{"yes" if sig else "no"}</td>'
                f"<td>{escape(str(s.get('why', '')))}</td></tr>")

    significant = [s for s in sugg if s.get("significant")]
    others = [s for s in sugg if not s.get("significant")]
    out = ["<h3>Diagnosis</h3>"]
    if significant and all(s.get("action") == "remove" for s in significant):
        out.append("<p>Nothing is missing; the record does not resolve these terms of the "
                   "model (drop them, best first):</p>")
        out.append(f"<table>{head}{''.join(row(s) for s in significant)}</table>")
    elif significant:
        out.append("<p>The model misses these effects (best first):</p>")
        out.append(f"<table>{head}{''.join(row(s) for s in significant)}</table>")
    else:
        out.append('<p class="ok">No missing effect is significant: the model explains the '
                   "measurement.</p>")
    if others:
        out.append(f"<details><summary>{len(others)} other candidate term(s) tried, not "
                   f"significant</summary><table>{head}{''.join(row(s) for s in others)}"
                   "</table></details>")
    return "\n".join(out)


def _method_section() -> str:
    return (
        '<h2 id="method">How to read this report</h2><ul>'
        "<li>The Allan deviation is the overlapping estimator; its band is the 95 % chi-square "
        "interval from the equivalent degrees of freedom. The fitted model is the sum of the "
        "terms' Allan variances; each term's own curve is dashed.</li>"
        "<li>z is the standardised residual of the measurement against the model at each "
        "\u03c4; \u03c7\u00b2/dof accounts for the correlation between neighbouring \u03c4.</li>"
        "<li>The discrete-time model is what a Kalman filter uses at the sample period. Its "
        "simulation is analysed like the measurement and overlaid (dotted): it should stay "
        "inside the measured band.</li></ul>")
