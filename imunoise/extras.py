"""Optional parts of imunoise and what to install for them.

The base install reads, analyses and serves; the ``fleet`` extra (Dask, pyarrow, fsspec) runs
the fleet commands, ``plot`` (matplotlib) draws results in a notebook, ``notebook`` adds pandas
and xarray for the results' tables and labelled arrays. A feature whose extra is missing
raises :class:`MissingExtra`: one line naming the extra to install (the command line's exit
code 2).
"""

from __future__ import annotations

import importlib

from imunoise.errors import UsageError

EXTRAS: dict[str, tuple[str, ...]] = {
    "fleet": ("dask", "distributed", "pyarrow", "fsspec"),
    "plot": ("matplotlib",),
    "notebook": ("pandas", "xarray"),
}
"""Each extra of ``pyproject.toml`` and the modules it provides."""


class MissingExtra(UsageError, ImportError):
    """A feature needs an optional extra that is not installed."""


def require(extra: str, feature: str, modules: tuple[str, ...] | None = None) -> None:
    """Import ``modules`` (default: every module of ``extra``), or raise :class:`MissingExtra`
    saying that ``feature`` needs ``pip install 'imunoise[EXTRA]'``."""
    for module in EXTRAS[extra] if modules is None else modules:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            missing = exc.name or module
            raise MissingExtra(f"{feature} needs the optional '{extra}' extra ({missing} is not "
                               f"installed): pip install 'imunoise[{extra}]'") from None
