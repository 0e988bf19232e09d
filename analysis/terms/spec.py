"""The one parser of model specifications, used by the command line, the live service and
the HTTP API alike.

Grammar (whitespace around items is ignored)::

    model  := entry ("," entry)*
    entry  := label (":" PARAM "=" VALUE)*
    label  := NAME | NAME "#" K

``NAME`` is a registered term (:mod:`imunoise.analysis.terms.registry`); ``PARAM=VALUE`` holds that
parameter of this entry fixed at ``VALUE`` (SI units). A term whose ``repeatable`` flag is set
may appear several times; each occurrence is its own entry with its own parameters, in the
order written. Occurrence ``K`` (counted from 1) of a term is labelled ``NAME#K`` for ``K > 1``
in outputs (``gauss_markov``, ``gauss_markov#2``) and may be written so in a specification,
where ``K`` must equal its occurrence. Examples::

    white,gauss_markov:T=100,gauss_markov,random_walk
    white,gauss_markov:T=100,gauss_markov#2:T=5

A term that is not repeatable appears at most once. Unknown terms, unknown parameters,
malformed or out-of-range values raise :class:`~imunoise.analysis.terms.base.TermError` naming what
is
valid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from imunoise.analysis.terms.base import TermError
from imunoise.analysis.terms.registry import TERMS, get_term


@dataclass(frozen=True)
class Entry:
    """One term of a model: its name, parameters held fixed and starting values (SI)."""

    name: str
    fixed: dict[str, float] = field(default_factory=dict)
    start: dict[str, float] | None = None

    def text(self) -> str:
        """This entry in the grammar (``name`` plus ``:P=V`` per fixed parameter)."""
        return self.name + "".join(f":{k}={v:.17g}" for k, v in self.fixed.items())


@dataclass(frozen=True)
class ModelSpec:
    """A parsed model: entries in order."""

    entries: tuple[Entry, ...]

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.entries]

    @property
    def labels(self) -> list[str]:
        """``name`` for a first occurrence, ``name#K`` for the K-th."""
        return labels(self.names)

    @property
    def fixed(self) -> dict[int, dict[str, float]]:
        """Fixed parameters by model index (entries with none left out)."""
        return {i: dict(e.fixed) for i, e in enumerate(self.entries) if e.fixed}

    def text(self) -> str:
        """The canonical specification string (parses back to an equal spec)."""
        return ",".join(e.text() for e in self.entries)

    def __len__(self) -> int:
        return len(self.entries)


def labels(names: Sequence[str]) -> list[str]:
    """Output labels of a model's terms: ``gauss_markov``, ``gauss_markov#2``, ..."""
    seen: dict[str, int] = {}
    out = []
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f"{n}#{seen[n]}")
    return out


def term_name(label: str) -> str:
    """The term name of a label or a specification entry (``gauss_markov#2:T=5`` ->
    ``gauss_markov``)."""
    return label.split(":")[0].partition("#")[0].strip()


def _valid() -> str:
    return ", ".join(TERMS)


def _check_names(names: Sequence[str]) -> None:
    if not names:
        raise TermError(f"empty model; valid terms: {_valid()}")
    unknown = [n for n in names if n not in TERMS]
    if unknown:
        raise TermError(f"unknown term(s) {', '.join(unknown)}; valid terms: {_valid()}")
    seen: set[str] = set()
    for n in names:
        if n in seen and not TERMS[n].repeatable:
            raise TermError(f"term {n!r} given twice (only "
                            f"{', '.join(t for t in TERMS if TERMS[t].repeatable)} may repeat)")
        seen.add(n)


def _entry(item: str, count: dict[str, int]) -> Entry:
    label, *assigns = item.split(":")
    label = label.strip()
    name, hash_, k_text = label.partition("#")
    name = name.strip()
    if name not in TERMS:
        raise TermError(f"unknown term(s) {name}; valid terms: {_valid()}")
    count[name] = count.get(name, 0) + 1
    if hash_:
        if not k_text.strip().isdigit() or int(k_text) != count[name]:
            raise TermError(f"{label!r}: occurrence {count[name]} of {name} is labelled "
                            f"{name if count[name] == 1 else f'{name}#{count[name]}'}")
    term = get_term(name)
    fixed: dict[str, float] = {}
    for a in assigns:
        key, eq, value = a.partition("=")
        key = key.strip()
        try:
            v = float(value)
        except ValueError:
            v = math.nan
            eq = ""
        if not eq or not key:
            raise TermError(f"bad fixed parameter {a!r} in {item!r}: use "
                            f"{name}:PARAM=VALUE") from None
        if key not in term.param_names:
            raise TermError(f"{name} has no parameter {key!r}; expected "
                            f"{', '.join(term.param_names)}")
        fixed[key] = v
    term.validate(fixed, partial=True)
    return Entry(name, fixed)


def parse_model(model: str | Sequence[Any] | ModelSpec) -> ModelSpec:
    """Parse a model given as a specification string, a list of names or labels, a list of
    ``(name, params)`` pairs (``params`` are starting values) or contract JSON
    ``[{"term": ..., "params": {...}}]``."""
    if isinstance(model, ModelSpec):
        return model
    count: dict[str, int] = {}
    entries: list[Entry] = []
    if isinstance(model, str):
        entries = [_entry(s.strip(), count) for s in model.split(",") if s.strip()]
    else:
        for item in model:
            if isinstance(item, str):
                entries.append(_entry(item.strip(), count))
            elif isinstance(item, dict):
                params = {k: float(v) for k, v in (item.get("params") or {}).items()}
                entries.append(_with_start(_entry(str(item["term"]), count), params))
            else:
                name, params = item
                e = _entry(str(name), count)
                entries.append(_with_start(e, None if params is None else
                                           {k: float(v) for k, v in dict(params).items()}))
    _check_names([e.name for e in entries])
    return ModelSpec(tuple(entries))


def _with_start(e: Entry, params: dict[str, float] | None) -> Entry:
    if params is not None:
        get_term(e.name).validate(params, partial=True)
    return Entry(e.name, e.fixed, params)


def parse_terms(text: str | Sequence[str]) -> list[str]:
    """Term names of a model (see :func:`parse_model`), validated."""
    return parse_model(text).names
