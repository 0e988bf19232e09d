"""HTTP API and dashboard: a thin layer over :mod:`analysis` and the acquisition state."""
