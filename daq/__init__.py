"""Hardware and files: transports, device drivers, simulators, acquisition, recorder, readers.

Produces :class:`core.blocks.SampleBlock` objects; holds no statistics.
"""
