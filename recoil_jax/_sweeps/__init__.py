"""Sweeps: the entry points `sweep`, `sweep_to_store` and `sweep_grid` (`sweep`) and
their settings (`settings`); designs as columns and batches (`batches`) and grids made a
chunk at a time (`grid`); the chunks they are cut into (`chunks`) and where those are
solved, on threads, devices or a Dask cluster (`dispatch`); memory checks (`memory`); the
results, in memory or in a store (`result`); and the normalised box a search or a fit
moves in (`space`).

May import: `_model`, `_campaigns`."""
