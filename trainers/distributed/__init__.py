"""Where work runs: seed-range shards, executors (in-process, Dask), child processes, and
``factorq sweep``."""
