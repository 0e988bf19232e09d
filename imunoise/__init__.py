"""imunoise: MEMS inertial sensor noise characterisation."""

__version__ = "0.1.0"

SOFTWARE = f"imunoise {__version__}"
"""The writer's name in recordings (MCAP header library and metadata ``software``)."""
