"""Parsers for option values shared by several commands."""

from __future__ import annotations

import re

from imunoise.errors import UsageError

_DURATION_UNITS = {"": 1.0, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0, "d": 86400.0}


def parse_duration(text: str) -> float:
    """Seconds from ``"90"``, ``"90s"``, ``"30m"``, ``"8h"`` or ``"1.5h"``."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-z]*)\s*", text.lower())
    if not match or match.group(2) not in _DURATION_UNITS:
        raise UsageError(f"bad duration {text!r}: use seconds or a unit, e.g. 90s, 30m, 8h")
    seconds = float(match.group(1)) * _DURATION_UNITS[match.group(2)]
    if seconds <= 0:
        raise UsageError(f"bad duration {text!r}: must be positive")
    return seconds
