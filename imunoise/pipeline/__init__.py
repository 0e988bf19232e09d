"""The analysis pipeline of a recording, independent of the command line.

- :mod:`~imunoise.pipeline.reading`: read a file, its timing model, keep the still stretches;
- :mod:`~imunoise.pipeline.channel_analysis`: Allan deviation, PSD and the default model fit of
  each channel (``analyze``);
- :mod:`~imunoise.pipeline.streamed_analysis`: the same for a file too long to hold;
- :mod:`~imunoise.pipeline.fitting`: one channel's fit and diagnosis (``fit``, ``diagnose``);
- :mod:`~imunoise.pipeline.channel_extras`: the discrete model, its check, the report's curves;
- :mod:`~imunoise.pipeline.documents`: the JSON documents (also the HTTP API's parts);
- :mod:`~imunoise.pipeline.assembly`: whole documents, also of several runs of one unit, and
  :mod:`~imunoise.pipeline.replicates_text` the readable report of those runs.

The commands under :mod:`imunoise.commands` parse arguments, call these and print.
"""
