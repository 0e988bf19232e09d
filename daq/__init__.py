"""Hardware and files: transports, device drivers, simulators, acquisition, recorder, readers.

Produces :class:`imunoise.core.blocks.SampleBlock` objects; holds no statistics.
"""
