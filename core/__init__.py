"""Types and constants that every other package shares.

Sample blocks, channel series, the timing model, units and physical constants, confidence levels
and the error hierarchy. ``core`` imports nothing from ``daq``, ``analysis``, ``live``, ``web`` or
``imunoise``; all of them may import it.
"""
