"""The noise model fitted when the user names none.

``imunoise analyze``, ``plan`` without ``--model``, the live service and the report's
diagnosis all fit this model, so that their numbers describe the same thing. It imports
nothing, so that the command line's help texts can name it without loading the numerics.
"""

from __future__ import annotations

DEFAULT_MODEL: tuple[str, ...] = ("white", "bias_instability", "random_walk")
"""Term names of the default model: white noise, bias instability (flicker) and rate random
walk."""

DEFAULT_MODEL_TEXT: str = ",".join(DEFAULT_MODEL)
""":data:`DEFAULT_MODEL` as the command line writes it: ``white,bias_instability,random_walk``."""
