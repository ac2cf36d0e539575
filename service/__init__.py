"""bcf.service: HTTP API (see the issues tracker; not implemented yet)."""
