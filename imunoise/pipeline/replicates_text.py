"""The readable report of several runs of one unit (``imunoise diagnose FILE1 FILE2 ...`` and
``imunoise.replicates(...).text()``): term sets, each run's error parts, shared shapes, per-run
amplitudes and the parameters that differ between runs."""

from __future__ import annotations

from typing import Any


def _value(v: float, unit: str) -> str:
    return f"{v:.4g} {unit}".removesuffix(" 1")


def _part(value: float | None) -> str:
    """An error part for the text, "n/a" where it could not be computed."""
    return "n/a" if value is None else f"{value:.3g}"


def replicates_text(key: str, units: str, res: Any) -> str:
    """Readable report of several runs of one unit: term sets, shared shapes, per-run
    amplitudes and the parameters that differ between runs."""
    from imunoise.analysis.terms import get_term, param_unit

    def unit(term: str, name: str) -> str:
        return param_unit(next(p for p in get_term(term).params if p.name == name), units)

    lines = [f"{key}: {len(res.runs)} runs of one unit"]
    if res.per_run_terms:
        for lab, terms in zip(res.runs, res.per_run_terms, strict=True):
            lines.append(f"  {lab}: the loop alone chooses {','.join(terms)}")
        common, n = res.common_terms
        lines.append(f"  most common term set ({n} of {len(res.runs)} runs): {','.join(common)}")
    lines.append(f"  model fitted to every run: {','.join(res.term_set)}")
    lines.append("  runs (allan chi2/dof alone -> shared shapes held | the run's own fit's psd "
                 "deviance/bin | hold-out chi2/dof)")
    parts = res.error_parts or [{} for _ in res.runs]
    for lab, free, tied, p in zip(res.runs, res.free_fits, res.tied_fits, parts, strict=True):
        psd = (p.get("psd") or {}).get("deviance_per_bin")
        holdout = p.get("holdout") or {}
        changes = holdout.get("changes_free") or {}
        # a change between the run's halves is a finding: the part with it fitted says
        # whether anything else is wrong
        found = "" if changes.get("chi2_per_dof") is None else \
            f" ({_part(changes['chi2_per_dof'])} with {', '.join(changes['params'])} " \
            f"fitted on each half)"
        lines.append(f"    {lab}: {free.chi2_per_dof:.3g} -> {tied.chi2_per_dof:.3g} | psd "
                     f"{_part(psd)} | hold-out {_part(holdout.get('chi2_per_dof'))}{found}")
    lines.append(f"  shared shape parameters (95 % intervals; chi2 of the runs against the "
                 f"pooled value, * = differ at family level {res.alpha:g})")
    if not res.shared:
        lines.append("    (the model has none)")
    for h in res.shared:
        u = unit(h.term, h.param)
        mark = "*" if h.differs else " "
        lines.append(f"  {mark} {h.term:17s} {h.param:5s} = {_value(h.pooled, u)} "
                     f"[{h.ci95[0]:.4g}, {h.ci95[1]:.4g}]  chi2 {h.q:.3g} on {h.dof} dof, "
                     f"p = {h.p_value:.2g}")
    lines.append("  per-run amplitudes (95 % intervals, shared shapes held)")
    for h in res.amplitudes:
        u = unit(h.term, h.param)
        mark = "*" if h.differs else " "
        vals = ", ".join("-" if e is None else f"<{e.ci95[1]:.3g}" if e.unresolved else
                         f"{e.value:.3g} [{e.ci95[0]:.3g}, {e.ci95[1]:.3g}]"
                         for e in res.tied_values(h))
        lines.append(f"  {mark} {h.term:17s} {h.param:5s} ({u}): {vals}  chi2 {h.q:.3g} on "
                     f"{h.dof} dof (own fits)")
    differ = res.differ
    if differ:
        lines.append("  differ between runs beyond their intervals")
        for h in differ:
            u = unit(h.term, h.param)
            values = res.per_run_values(h)
            vals = ", ".join("-" if e is None else f"{e.value:.4g}" for e in values)
            peaks = [str(r + 1) for r, e in enumerate(values) if e is not None
                     and e.source == "psd"]
            src = f" (runs {', '.join(peaks)} at their spectrum's peak)" if peaks else ""
            lines.append(f"    {h.term} {h.param}: {vals} {u} by run{src}; chi2 = {h.q:.3g} "
                         f"on {h.dof} dof, p = {h.p_value:.2g}")
    else:
        lines.append("  no parameter differs between runs beyond its interval")
    return "\n".join(lines)
