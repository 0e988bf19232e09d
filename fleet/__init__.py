"""Fleets of recordings: the Parquet catalogue of per-file results and the fleet view over it.

``imunoise.fleet.catalog`` writes and reads the catalogue (one row per file and channel);
``imunoise.fleet.view`` turns it into the fleet summary (populations, outliers, units over time,
limits,
replicates); ``fleet.html`` renders that summary as a self-contained page. The analysis of one
file and the Dask orchestration belong to the command line (``imunoise fleet``).
"""
