"""The error hierarchy: every error imunoise raises on purpose derives from ``ImunoiseError``.

``str(error)`` is one line meant for the user. ``exit_code`` is what the command line returns
for it: 2 for bad input or usage (nothing was written half-way), 1 for a failure while running.
"""

from __future__ import annotations


class ImunoiseError(Exception):
    """Base of the project's errors: a failure while running (device lost, disk full)."""

    exit_code = 1


class InputError(ImunoiseError, ValueError):
    """Bad input or usage: an unreadable file, an unknown term, channel or option value."""

    exit_code = 2
