"""The workflow layer: configuration schema, run directory, stages as dask graphs, clusters, CLI."""
