"""Hardware and files: transports, device drivers, simulators, acquisition, recorder, readers.

Produces :class:`daq.blocks.SampleBlock` objects; holds no statistics.
"""
