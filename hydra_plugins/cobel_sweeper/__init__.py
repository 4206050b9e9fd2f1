"""Hydra sweeper plugin ``cobel``: resumable, failure-tolerant cartesian sweeps (see cobel_sweeper)."""
