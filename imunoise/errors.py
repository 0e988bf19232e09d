"""Errors that the command line turns into one line on stderr and an exit code."""


class UsageError(Exception):
    """Bad usage or bad input: exit code 2, nothing written half-way."""

    exit_code = 2


class RuntimeFailure(Exception):
    """The command was well-formed but failed while running (device lost, disk full): exit 1."""

    exit_code = 1
