"""Many sessions at once on Dask distributed, re-running only what changed, and the fleet summary."""
