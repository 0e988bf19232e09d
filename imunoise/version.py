"""The version of imunoise and the name it writes into recordings."""

__version__ = "0.1.0"

SOFTWARE = f"imunoise {__version__}"
"""The writer's name in recordings (MCAP header library and metadata ``software``)."""
