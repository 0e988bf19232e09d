"""imunoise: MEMS inertial sensor noise characterisation.

The Python API (docs/python.md) reads a recording as ``imunoise analyze`` does and returns
results that plot, tabulate and give the command line's JSON documents::

    import imunoise
    rec = imunoise.read("run1.mcap")
    curve = imunoise.oadev(rec["gyro_x"])
    model = imunoise.fit(curve, "white,bias_instability,random_walk")
    dx = imunoise.diagnose(rec["gyro_x"], "white,bias_instability,random_walk")

The API loads on first use (numpy, scipy and the readers are not imported by
``import imunoise`` itself), so the command line starts as fast as without it.
"""

from __future__ import annotations

from typing import Any

from imunoise.version import SOFTWARE, __version__

_API = ("read", "oadev", "psd", "fit", "diagnose", "replicates", "analyze", "DEFAULT_MODEL",
        "Recording", "Channel", "AllanResult", "PsdResult", "FitReport", "Diagnosis",
        "Replicates")

__all__ = ["SOFTWARE", "__version__", *_API]


def __getattr__(name: str) -> Any:
    """The API's names, imported from :mod:`imunoise.api` when first asked for."""
    if name in _API:
        from imunoise import api

        return getattr(api, name)
    raise AttributeError(f"module 'imunoise' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
