"""The live runtime of ``imunoise serve``: the service that moves sample blocks from a source
to the recorder and the rolling analyzers, and reports its state to the HTTP layer.

``live`` may import ``core``, ``analysis`` and ``daq``; ``web`` and ``imunoise`` build on it.
"""
