"""Many sequences at once: manifest, one task per sequence on Dask, batch summary."""
