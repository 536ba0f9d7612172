"""magcal batch: plan one fit per log, run them locally or on a Dask cluster, and report them."""
