"""The JSON documents of the results, one place for the command line and the HTTP API.

:mod:`imunoise.pipeline.documents` builds the command line's documents (``analyze``, ``fit``,
``diagnose``) and the parts every document shares (a fitted model's entries, its error, z on
the curve, strict numbers); :mod:`imunoise.web.views.live` builds the API's views of a live channel
from those same parts, so live and batch numbers cannot be written out differently.
"""
