"""bcf.service: the HTTP API over bcf.jobs (FastAPI): `app.create_app(settings)`; run by `bcf serve`."""
