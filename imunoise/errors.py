"""Errors that the command line turns into one line on stderr and an exit code."""

from imunoise.core.errors import ImunoiseError, InputError


class UsageError(InputError):
    """Bad usage or bad input: exit code 2, nothing written half-way."""


class RuntimeFailure(ImunoiseError):
    """The command was well-formed but failed while running (device lost, disk full): exit 1."""
