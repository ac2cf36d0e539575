"""bcf.jobs: job queue and workers (see the issues tracker; not implemented yet)."""
