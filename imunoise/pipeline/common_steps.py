"""``common_steps`` in a model specification: the steps a record's channels of one kind take
together, found on the record and taken out of the channel before it is fitted
(:mod:`imunoise.analysis.common_steps`).

The removal is no noise term: it changes the series, so the analysis never sees the name. The
commands take it out of the specification (:func:`split_model`), find the steps on the channels
that share the fitted channel's time base and units (:func:`steps_of`, on the record before
``--skip``/``--split``, as the chain shape is), correct the channel (:func:`remove_steps`),
and put the name back where the output lists the model (:func:`add_to_document`): ``fit``
and ``diagnose`` with ``--model ...,common_steps`` on one half of a night find and take out
that half's own steps.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from imunoise.analysis.common_steps import TERM, CommonSteps, find_common_steps
from imunoise.core.record import Record
from imunoise.core.series import ChannelSeries
from imunoise.errors import UsageError
from imunoise.pipeline.cross_channel import time_base_group


def split_model(model_text: str) -> tuple[str, bool]:
    """``(model without common_steps, whether it named common_steps)``; a usage error where
    the name carries parameters (the steps are found, not fitted)."""
    kept, named = [], False
    for token in model_text.split(","):
        name = token.strip()
        if name.split(":")[0].strip() == TERM:
            if ":" in name:
                raise UsageError(f"{TERM} takes no parameters (the steps are found on the "
                                 f"record, not fitted); got {name!r}")
            named = True
        else:
            kept.append(token)
    rest = ",".join(kept)
    if named and not rest.strip():
        raise UsageError(f"{TERM} removes steps from the channel: name the noise terms to "
                         f"fit beside it (for example white,bias_instability,random_walk,"
                         f"{TERM})")
    return rest, named


def steps_of(record: Record, key: str, group: list[str]) -> CommonSteps | None:
    """The :class:`imunoise.analysis.common_steps.CommonSteps` of the channels of ``group``
    (``key`` first) that share ``key``'s time base and units, or None where no other channel
    does. Call before ``--skip``/``--split`` cut ``key``."""
    series = record.channels
    units = series[key].units
    # a channel on key's time base: the pair is one group (another device's is not)
    same = [k for k in group if k in series and series[k].units == units
            and (k == key or time_base_group(series, [key, k]) == [key, k])]
    if len(same) < 2:
        return None
    x = np.column_stack([np.asarray(series[k].values, dtype=np.float64) for k in same])
    return find_common_steps(x, series[key].fs_hz, same, series[key].segment_starts)


def required(steps: CommonSteps | None, key: str, units: str) -> CommonSteps:
    """``steps``, or a usage error where the model names ``common_steps`` and no other channel
    of the record shares ``key``'s time base and units (``steps`` None)."""
    if steps is None:
        raise UsageError(f"{TERM}: no other channel of this record shares {key}'s time base "
                         f"and units ({units}), so steps common to them cannot be told from "
                         f"{key}'s own wander")
    return steps


def remove_steps(record: Record, key: str, steps: CommonSteps) -> None:
    """Channel ``key`` of ``record`` with its common steps taken out (in place)."""
    series = record.channels[key]
    record.channels[key] = dataclasses.replace(series,
                                               values=steps.corrected(series.values, key))


def corrected_copy(record: Record, key: str, steps: CommonSteps) -> Record:
    """A copy of ``record`` whose channel ``key`` has its common steps taken out."""
    copy = dataclasses.replace(record, channels=dict(record.channels),
                               warnings=list(record.warnings))
    remove_steps(copy, key, steps)
    return copy


def add_to_document(doc: dict[str, Any], steps: CommonSteps, key: str) -> None:
    """``doc``'s model lists ``common_steps`` (no parameters) and ``doc["common_steps"]`` the
    steps taken out of ``key``."""
    doc.setdefault("model", []).append({"term": TERM, "params": {}, "ci95": {},
                                        "unresolved": []})
    doc["common_steps"] = steps.to_dict(key)


def keep_in_applies(suggestions: list[Any]) -> None:
    """Each suggestion's ``apply.model`` keeps ``common_steps``: the analysis saw the model
    without it."""
    for s in suggestions:
        model = str(s.apply.get("model", ""))
        if model and TERM not in [t.strip() for t in model.split(",")]:
            s.apply["model"] = f"{model},{TERM}"


def halves_corrected(raw: ChannelSeries, record: Record, key: str, channels: list[str]
                     ) -> np.ndarray:
    """``key``'s samples with each half's own common steps taken out: the steps searched in
    each half of the record alone (``channels`` of ``record`` on ``raw``'s time base, ``raw``
    standing for ``key``), as a fit of that half would find them."""
    x = np.column_stack([np.asarray(raw.values if k == key else record.channels[k].values,
                                    dtype=np.float64) for k in channels])
    starts = np.asarray(raw.segment_starts, dtype=np.int64)
    out = np.array(raw.values, dtype=np.float64, copy=True)
    mid = x.shape[0] // 2
    for a, b in ((0, mid), (mid, x.shape[0])):
        inner = np.concatenate(([0], starts[(starts > a) & (starts < b)] - a))
        half = find_common_steps(x[a:b], raw.fs_hz, channels, inner)
        out[a:b] = half.corrected(out[a:b], key)
    return out


def rank_removal(diag: Any, corrected: Record, raw: ChannelSeries, key: str,
                 steps: CommonSteps, model_text: str, skip_s: float,
                 split_s: list[float]) -> list[Any]:
    """``diag.suggestions`` with the ``common_steps`` suggestion in its place
    (:func:`imunoise.analysis.diagnosis.common_steps.steps_suggestion`): the model
    ``model_text`` fitted to ``corrected`` (:func:`corrected_copy` of the record before the
    cuts; cut here as the diagnosed channel was) and its error parts. Its hold-out part fits
    each half with that half's own steps taken out (:func:`halves_corrected`, ``raw`` being
    ``key`` as read), as a fit of the half does; with ``--skip`` or ``--split`` the halves of
    the corrected channel are used instead."""
    from imunoise.analysis.diagnosis.common_steps import ranked_in, steps_suggestion
    from imunoise.analysis.model_error import holdout_part
    from imunoise.pipeline.fitting import fit_channel, fit_error_parts
    from imunoise.pipeline.reading import apply_window
    from imunoise.pipeline.workers import cpu_job_map

    apply_window(corrected, key, skip_s, split_s)
    result, _ = fit_channel(corrected, key, model_text)
    per_half = not skip_s and not split_s
    # the corrected channel's own halves only where each half's steps cannot be searched
    _, parts = fit_error_parts(corrected, key, model_text, result, holdout=not per_half)
    if per_half:
        values = halves_corrected(raw, corrected, key, steps.channels)
        parts["holdout"] = holdout_part(values, raw.fs_hz, model_text, result,
                                        segment_starts=raw.segment_starts,
                                        job_map=cpu_job_map())
    new = steps_suggestion(diag, steps, key, result, parts, model_text,
                           corrected.channels[key].units)
    return ranked_in(diag.suggestions, new)


def steps_line(steps: CommonSteps, key: str, units: str) -> str:
    """One line of text: the steps taken out of ``key``."""
    own = steps.of(key)
    if not steps.steps:
        return f"{TERM}: no step found in {', '.join(steps.channels)}; {key} is fitted as read"
    if not own:
        return (f"{TERM}: none taken out of {key} ({len(steps.steps)} found in "
                f"{', '.join(steps.channels)}, none lasting beyond {key}'s own noise)")
    told = ", ".join(f"{s.t_s:.0f} s {s.sizes[key]:+.3g} {units}" for s in own)
    return (f"{TERM}: {len(own)} step(s) taken out of {key} (found together in "
            f"{', '.join(steps.channels)}): {told}")
