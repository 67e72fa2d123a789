"""admc.pipeline.engine: cached tasks run once each, locally, on a dask cluster or under SLURM; knows no stage."""
