"""The fleet view: what a catalogue says about a population of units.

:func:`fleet_summary` reads the catalogue rows and returns one JSON-ready document (served as
``/fleet`` and rendered by ``imunoise fleet-report``):

* ``populations``: per sensor model and channel, every unit's value of each coefficient (its
  recordings pooled, :func:`imunoise.analysis.fleet_stats.pool_replicates`) and the units that are
  outliers against the others (modified z-score on log values, |M| > 3.5);
* ``units``: per unit and channel, each coefficient over time with its 95 % interval, the
  pooled value with Cochran's test that the recordings agree, and whether the latest
  recording's interval lies wholly above the earliest's (``grew``);
* ``limits``: with user limits (:func:`load_limits`), pass / fail / marginal per recording;
* ``failed``: the files that could not be analysed, with their errors.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from imunoise.analysis.fleet_stats import (
    MIN_POPULATION,
    OUTLIER_M,
    grew,
    limit_verdict,
    pool_replicates,
    robust_outliers,
)
from imunoise.core.units import from_conventional, param_units, si_unit
from imunoise.fleet.catalog import COEFFICIENTS, read_catalog

OUTLIER_TEST = (f"modified z-score (Iglewicz and Hoaglin 1993) of log values against the "
                f"population's median and MAD; outlier when |M| > {OUTLIER_M}, with at least "
                f"{MIN_POPULATION} units")
AGREEMENT_TEST = "Cochran's Q on log values (chi-square, k-1 dof); agree when p >= 0.05"

_COLUMNS = ["file", "file_hash", "analysed_at", "topic", "status", "error", "unit",
            "sensor_model", "channel", "kind", "start_time", "duration_s", "chi2_per_dof",
            "significant_suggestions"] + [
    f"{p}{s}" for p in COEFFICIENTS for s in ("", "_lo95", "_hi95", "_resolved")]


class LimitsError(ValueError):
    """A limits file that cannot be used."""


def load_limits(path: str | Path) -> dict[str, dict[str, dict[str, dict[str, float]]]]:
    """Read a limits YAML file into ``{model: {kind or channel: {coefficient: {"max": SI,
    "min": SI}}}}``.

    The file maps a sensor model (``"*"`` for any) to ``gyro``/``accel`` or a channel name, to
    a coefficient (N, B, K) with ``max`` and/or ``min`` and an optional ``unit`` (the SI or the
    conventional unit label, e.g. ``deg/sqrt(h)``; SI when absent)."""
    import yaml

    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise LimitsError(f"{path}: {exc}".splitlines()[0]) from None
    if not isinstance(doc, dict):
        raise LimitsError(f"{path}: expected a mapping of sensor model -> kind -> coefficient")
    out: dict = {}
    for model, kinds in doc.items():
        if not isinstance(kinds, dict):
            raise LimitsError(f"{path}: {model}: expected gyro/accel or channel names")
        for where, coefs in kinds.items():
            kind = "gyro" if str(where).startswith("gyro") else "accel" \
                if str(where).startswith("accel") else None
            if kind is None or not isinstance(coefs, dict):
                raise LimitsError(f"{path}: {model}.{where}: expected gyro, accel or a channel "
                                  "name mapping to coefficients")
            for coef, spec in coefs.items():
                out.setdefault(str(model), {}).setdefault(str(where), {})[str(coef)] = \
                    _limit(path, f"{model}.{where}.{coef}", str(coef), kind, spec)
    return out


def _limit(path: str | Path, where: str, coef: str, kind: str, spec: Any) -> dict[str, float]:
    if coef not in COEFFICIENTS:
        raise LimitsError(f"{path}: {where}: unknown coefficient; known: "
                          f"{', '.join(COEFFICIENTS)}")
    if not isinstance(spec, dict) or not ({"max", "min"} & set(spec)):
        raise LimitsError(f"{path}: {where}: give max and/or min (and optionally unit)")
    units = param_units(coef, kind)
    unit = spec.get("unit", units.si)
    if unit not in (units.si, units.conventional):
        raise LimitsError(f"{path}: {where}: unit {unit!r} is neither {units.si!r} nor "
                          f"{units.conventional!r}")
    out = {}
    for bound in ("max", "min"):
        if bound in spec:
            try:
                v = float(spec[bound])
            except (TypeError, ValueError):
                raise LimitsError(f"{path}: {where}.{bound}: not a number") from None
            out[bound] = float(from_conventional(coef, kind, v)) if unit != units.si else v
    return out


def _limits_for(limits: Mapping, model: str, channel: str, kind: str) -> dict:
    """The limits that apply to a channel: the model's over ``*``, a channel over its kind."""
    found: dict = {}
    for m in ("*", model):
        for where in (kind, channel):
            for coef, spec in (limits.get(m, {}).get(where) or {}).items():
                found[coef] = spec
    return found


def _iso(t: Any) -> str | None:
    return t.isoformat() if isinstance(t, datetime) else None


def _num(v: Any) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


def _history(rows: list[dict], coef: str) -> list[dict]:
    out = []
    for r in sorted(rows, key=lambda r: (r["start_time"] is None, r["start_time"] or 0)):
        out.append({"start_time": _iso(r["start_time"]), "file": r["file"],
                    "value": _num(r[coef]),
                    "ci95": [_num(r[f"{coef}_lo95"]), _num(r[f"{coef}_hi95"])],
                    "resolved": bool(r[f"{coef}_resolved"])})
    return out


def _unit_entry(unit: str, model: str, channel: str, kind: str, rows: list[dict]) -> dict:
    entry: dict[str, Any] = {"unit": unit, "sensor_model": model, "channel": channel,
                             "kind": kind, "recordings": len(rows), "coefficients": {}}
    for coef in COEFFICIENTS:
        hist = _history(rows, coef)
        res = [h for h in hist if h["resolved"] and h["value"] is not None]
        pooled = pool_replicates(np.array([h["value"] for h in res], dtype=np.float64),
                                 np.array([h["ci95"][0] for h in res], dtype=np.float64),
                                 np.array([h["ci95"][1] for h in res], dtype=np.float64)) \
            if res else None
        entry["coefficients"][coef] = {
            "si_unit": si_unit(coef, kind),
            "history": hist,
            "pooled": pooled.to_dict() if pooled else None,
            "unresolved_recordings": len(hist) - len(res),
            "grew": grew(tuple(res[0]["ci95"]), tuple(res[-1]["ci95"]))
            if len(res) >= 2 else False,
        }
    return entry


def _population(model: str, channel: str, kind: str, units: list[dict]) -> dict:
    out: dict[str, Any] = {"sensor_model": model, "channel": channel, "kind": kind,
                           "units": len(units), "coefficients": {}}
    for coef in COEFFICIENTS:
        vals = np.array([(u["coefficients"][coef]["pooled"] or {}).get("value", np.nan)
                         for u in units], dtype=np.float64)
        m, flag = robust_outliers(vals)
        finite = vals[np.isfinite(vals)]
        out["coefficients"][coef] = {
            "si_unit": si_unit(coef, kind),
            "median": float(np.median(finite)) if finite.size else None,
            "test": OUTLIER_TEST,
            "units": [{"unit": u["unit"], "value": _num(v), "m_score": _num(mi),
                       "ci95": (u["coefficients"][coef]["pooled"] or {}).get("ci95"),
                       "outlier": bool(f)}
                      for u, v, mi, f in zip(units, vals, m, flag, strict=True)],
        }
    return out


def _limit_rows(rows: list[dict], limits: Mapping) -> list[dict]:
    out = []
    for r in rows:
        for coef, spec in _limits_for(limits, r["sensor_model"], r["channel"], r["kind"]).items():
            value = r[coef] if r[f"{coef}_resolved"] else np.nan
            verdict = limit_verdict(float(value if value is not None else np.nan),
                                    float(r[f"{coef}_lo95"] or np.nan),
                                    float(r[f"{coef}_hi95"] or np.nan),
                                    spec.get("max"), spec.get("min"))
            out.append({"file": r["file"], "unit": r["unit"], "sensor_model": r["sensor_model"],
                        "channel": r["channel"], "coefficient": coef, "si_unit":
                        si_unit(coef, r["kind"]), "value": _num(value),
                        "ci95": [_num(r[f"{coef}_lo95"]), _num(r[f"{coef}_hi95"])],
                        "max": spec.get("max"), "min": spec.get("min"), "verdict": verdict})
    return out


def _latest(rows: list[dict]) -> list[dict]:
    """One row per recording and channel: the latest analysis of the same content (two runs
    over the same files, or a copy under another name, count once)."""
    by_key: dict[tuple, dict] = {}
    for r in sorted(rows, key=lambda r: r["analysed_at"] or datetime.min.replace(tzinfo=UTC)):
        by_key[(r["file_hash"] or r["file"], r["topic"], r["channel"])] = r
    return list(by_key.values())


def fleet_summary(folder: str | Path, limits: Mapping | None = None) -> dict[str, Any]:
    """The fleet document of a catalogue folder (see the module notes)."""
    rows = read_catalog(folder, _COLUMNS).to_pylist()
    ok = _latest([r for r in rows if r["status"] == "ok" and r["channel"]])
    failed = {r["file"]: r["error"] for r in rows if r["status"] == "failed"}
    good_files = {r["file"] for r in ok}
    groups: dict[tuple[str, str, str], dict[str, list[dict]]] = defaultdict(
        lambda: defaultdict(list))
    for r in ok:
        groups[(r["sensor_model"] or "unknown", r["channel"], r["kind"])][r["unit"]].append(r)
    populations, units = [], []
    for (model, channel, kind), by_unit in sorted(groups.items()):
        entries = [_unit_entry(u, model, channel, kind, rs) for u, rs in sorted(by_unit.items())]
        units += entries
        populations.append(_population(model, channel, kind, entries))
    outliers = [{"sensor_model": p["sensor_model"], "channel": p["channel"], "coefficient": c,
                 "unit": u["unit"], "value": u["value"], "m_score": u["m_score"]}
                for p in populations for c, d in p["coefficients"].items()
                for u in d["units"] if u["outlier"]]
    grown = [{"unit": u["unit"], "sensor_model": u["sensor_model"], "channel": u["channel"],
              "coefficient": c} for u in units for c, d in u["coefficients"].items()
             if d["grew"]]
    disagree = [{"unit": u["unit"], "sensor_model": u["sensor_model"],
                 "channel": u["channel"], "coefficient": c, "p_value": d["pooled"]["p_value"]}
                for u in units for c, d in u["coefficients"].items()
                if d["pooled"] and d["pooled"]["agree"] is False]
    return _json_safe({
        "catalog": str(folder),
        "files": len(good_files | set(failed)), "files_ok": len(good_files),
        "files_failed": len(set(failed) - good_files), "rows": len(rows),
        "outlier_test": OUTLIER_TEST, "agreement_test": AGREEMENT_TEST,
        "failed": [{"file": f, "error": e} for f, e in sorted(failed.items())
                   if f not in good_files],
        "populations": populations, "units": units, "outliers": outliers, "grew": grown,
        "disagree": disagree,
        "limits": _limit_rows(ok, limits) if limits else [],
    })


def _json_safe(obj: Any) -> Any:
    """Non-finite floats as None, all the way down (JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    return obj
