"""trainers: what users run (the paper's experiment, reports, baselines, the `factorq` CLI)."""
