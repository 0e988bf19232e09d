"""imunoise: MEMS inertial sensor noise characterisation."""

__version__ = "0.1.0"
