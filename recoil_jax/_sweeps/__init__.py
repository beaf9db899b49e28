"""Sweeps: designs as batches, grids streamed a chunk at a time, memory checks, chunks on
threads or a Dask cluster, and a sweep kept in a store (`sweep`); the normalised box a
search or a fit moves in (`space`).

May import: `_model`, `_campaigns`."""
