"""The HTTP API (FastAPI): submit materials, follow jobs, fetch reports and artifacts.

`create_app(settings)` builds the application; `bcf serve` runs it with uvicorn. The API only submits and
reads jobs through `bcf.jobs`; workers (`bcf worker`, or the ones `bcf serve` starts) do the compressing.
"""

from __future__ import annotations

import json
import secrets
import tempfile
import zipfile
from pathlib import Path
from typing import Annotated, Any, Optional

from fastapi import Depends, FastAPI, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ValidationError
from starlette.background import BackgroundTask
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from bcf.core import JobOptions, __version__
from bcf.jobs.queue import JobQueue
from bcf.jobs.records import FINAL_STATES, Job, JobState
from bcf.jobs.settings import Settings
from bcf.jobs.store import StoreUnavailable
from bcf.service.metrics import prometheus_text
from bcf.service.uploads import ROLE_FIELDS, BadUpload, UploadedFile, submit_upload

__all__ = ["JobList", "create_app"]

FORM_FIELDS = (*ROLE_FIELDS, "material", "options")


class JobList(BaseModel):
    jobs: list[Job]
    total: int
    offset: int
    limit: int


class _BodyTooLarge(Exception):
    pass


# Paths anyone may read: liveness and the API description.
OPEN_PATHS = frozenset({"/healthz", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"})


def _token_accepted(given: str, tokens: list[str]) -> bool:
    return any(secrets.compare_digest(given.encode(), t.encode()) for t in tokens)


def _token_ok(headers: dict[bytes, bytes], tokens: list[str]) -> bool:
    scheme, _, given = headers.get(b"authorization", b"").decode("latin-1").partition(" ")
    return scheme.lower() == "bearer" and _token_accepted(given, tokens)


class RequestGate:
    """In front of the app, before any body is read: the bearer token (401), then the body size (413) by
    Content-Length and by counting as it streams in (chunked uploads). Checking here, not in a FastAPI
    dependency, means an unauthenticated or oversized upload is never parsed or spooled to disk."""

    def __init__(self, app: ASGIApp, settings: Settings):
        self.app = app
        self.tokens = settings.api_tokens
        self.limit = int(settings.max_upload_mb * 2**20)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope["headers"])
        if self.tokens and scope["path"] not in OPEN_PATHS and not _token_ok(headers, self.tokens):
            await _send_error(send, 401, UNAUTHORISED, [(b"www-authenticate", b"Bearer")])
            return
        length = headers.get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.limit:
            await _send_error(send, 413, self._too_large())
            return
        seen = 0
        started = rejected = False

        async def counting_receive() -> Message:
            nonlocal seen, rejected
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    if not started:  # answer now: the app turns any error inside form parsing into a 400
                        await _send_error(send, 413, self._too_large())
                        rejected = True
                    raise _BodyTooLarge()
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if rejected:
                return  # the 413 went out already; drop the app's own answer to the aborted body
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counting_receive, tracking_send)
        except _BodyTooLarge:
            if not started and not rejected:
                await _send_error(send, 413, self._too_large())

    def _too_large(self) -> str:
        return f"request body larger than the limit of {self.limit / 2**20:.0f} MiB (BCF_MAX_UPLOAD_MB)"


UNAUTHORISED = "missing or wrong bearer token (Authorization: Bearer <one of BCF_API_TOKENS>)"


async def _send_error(send: Send, status: int, detail: str, headers: Optional[list] = None) -> None:
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"connection", b"close"), *(headers or [])]})
    await send({"type": "http.response.body", "body": json.dumps({"detail": detail}).encode()})


def _options(text: Optional[str]) -> JobOptions:
    if text is None or not text.strip():
        return JobOptions()
    try:
        options = JobOptions.model_validate_json(text)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'options'}: {e['msg']}" for e in exc.errors())
        raise BadUpload(422, f"options: {problems}") from None
    if "device" in options.model_fields_set:
        raise BadUpload(422, "options: device is chosen by the worker that runs the job ('bcf worker --device'); "
                             "remove it from the options")
    return options


def create_app(settings: Settings, queue: Optional[JobQueue] = None) -> FastAPI:
    queue = queue or JobQueue(settings)
    app = FastAPI(title="bcf", version=__version__,
                  description="Neural block-compressed features (BC6H) for PBR materials: submit a texture set, "
                              "get BC6H feature textures, MLP weights and a quality report.")
    app.state.queue = queue
    bearer = HTTPBearer(auto_error=False, description="one of BCF_API_TOKENS")

    def authorised(credentials: Optional[HTTPAuthorizationCredentials] = Depends(bearer)) -> None:
        """Checked again here (RequestGate checks first) so the app is safe without the gate too, and so
        OpenAPI shows the bearer scheme."""
        if not settings.api_tokens:
            return  # no tokens: `bcf serve` listens on 127.0.0.1 only
        if not _token_accepted(credentials.credentials if credentials else "", settings.api_tokens):
            raise HTTPException(401, UNAUTHORISED, headers={"WWW-Authenticate": "Bearer"})

    def find(job_id: str) -> Job:
        job = queue.store.get(job_id)
        if job is None:
            raise HTTPException(404, f"no job {job_id!r}")
        return job

    def succeeded(job_id: str) -> Job:
        job = find(job_id)
        if job.state != "succeeded":
            raise HTTPException(409, f"job {job.id} is {job.state}; results exist once it has succeeded"
                                + (f" (error: {job.error})" if job.error else ""))
        return job

    @app.exception_handler(BadUpload)
    async def bad_upload(request: Request, exc: BadUpload) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=exc.status)

    @app.exception_handler(StoreUnavailable)
    async def store_down(request: Request, exc: StoreUnavailable) -> JSONResponse:
        return JSONResponse({"detail": f"job store unavailable, retry later: {exc}"}, status_code=503,
                            headers={"Retry-After": "5"})

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        return JSONResponse({"detail": problems}, status_code=422)

    guarded = [Depends(authorised)]

    @app.get("/healthz", tags=["service"])
    def healthz() -> dict[str, Any]:
        """Liveness and whether the job store answers (no token needed)."""
        try:
            queue.store.ping()
        except StoreUnavailable as exc:
            return JSONResponse({"status": "unavailable", "detail": str(exc)}, status_code=503)  # type: ignore
        return {"status": "ok", "version": __version__, "mode": "farm" if settings.farm_mode else "embedded"}

    @app.get("/metrics", tags=["service"], dependencies=guarded, response_class=PlainTextResponse)
    def metrics() -> PlainTextResponse:
        """Prometheus text format: jobs by state, queue depth, job durations."""
        return PlainTextResponse(prometheus_text(queue), media_type="text/plain; version=0.0.4")

    @app.post("/v1/jobs", tags=["jobs"], status_code=202, dependencies=guarded, response_model=Job,
              responses={200: {"description": "the same inputs and options were submitted before: that job"},
                         413: {"description": "upload over BCF_MAX_UPLOAD_MB"},
                         415: {"description": "a file is not an accepted image (or the material not a zip)"},
                         422: {"description": "the material or the options cannot be used"}})
    async def submit(request: Request,
                     albedo: Optional[UploadFile] = File(None, description="base colour, sRGB"),
                     normal: Optional[UploadFile] = File(None, description="tangent-space normal map"),
                     arm: Optional[UploadFile] = File(None, description="packed AO / roughness / metalness"),
                     ao: Optional[UploadFile] = File(None), roughness: Optional[UploadFile] = File(None),
                     metalness: Optional[UploadFile] = File(None),
                     material: Optional[UploadFile] = File(None, description="zip of a material folder, "
                                                                             "instead of the files per role"),
                     options: Optional[str] = Form(None, description='JSON, e.g. {"preset": "fast"}')) -> Any:
        """Submit a material: files per role, or a zip. 202 with the new job, or 200 with the existing job when
        the same files and options were submitted before (and did not fail)."""
        form = await request.form()
        unknown = sorted(set(form.keys()) - set(FORM_FIELDS))
        if unknown:
            raise BadUpload(400, f"unknown form field(s) {', '.join(unknown)}; expected "
                                 f"{', '.join(FORM_FIELDS)}")
        if len(form.getlist("options")) > 1 or any(len(form.getlist(f)) > 1 for f in FORM_FIELDS):
            raise BadUpload(400, "each form field may appear once")
        parsed = _options(options)
        given = {"albedo": albedo, "normal": normal, "arm": arm, "ao": ao, "roughness": roughness,
                 "metalness": metalness, "material": material}
        uploads = [UploadedFile(field, f.filename, f.file) for field, f in given.items() if f is not None]
        job, created = await run_in_threadpool(submit_upload, queue, uploads, parsed)
        return JSONResponse(job.model_dump(mode="json"), status_code=202 if created else 200,
                            headers={"Location": f"/v1/jobs/{job.id}"})

    @app.get("/v1/jobs", tags=["jobs"], dependencies=guarded, response_model=JobList)
    def list_jobs(state: Annotated[Optional[list[JobState]], Query(description="repeat to give several")] = None,
                  offset: Annotated[int, Query(ge=0)] = 0,
                  limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> JobList:
        """Jobs, newest first."""
        jobs, total = queue.store.list(set(state) if state else None, offset, limit)
        return JobList(jobs=jobs, total=total, offset=offset, limit=limit)

    @app.get("/v1/jobs/{job_id}", tags=["jobs"], dependencies=guarded, response_model=Job)
    def get_job(job_id: str) -> Job:
        return find(job_id)

    @app.delete("/v1/jobs/{job_id}", tags=["jobs"], dependencies=guarded, response_model=Job,
                responses={409: {"description": "the job already finished"}})
    def cancel_job(job_id: str) -> Any:
        """Cancel: a queued job at once, a running one within a few seconds (watch its state)."""
        find(job_id)
        job = queue.cancel(job_id)
        if job is None:
            raise HTTPException(404, f"no job {job_id!r}")
        if job.state in FINAL_STATES and job.state != "cancelled":
            raise HTTPException(409, f"job {job.id} already {job.state}; nothing to cancel")
        return JSONResponse(job.model_dump(mode="json"), status_code=200 if job.state == "cancelled" else 202)

    @app.get("/v1/jobs/{job_id}/report", tags=["results"], dependencies=guarded)
    def get_report(job_id: str) -> FileResponse:
        """The job's report.json (the schema is in docs/FORMAT.md)."""
        job = succeeded(job_id)
        return FileResponse(queue.artifacts_path(job.id) / "report.json", media_type="application/json")

    @app.get("/v1/jobs/{job_id}/artifacts", tags=["results"], dependencies=guarded,
             response_class=FileResponse)
    def get_artifacts(job_id: str) -> FileResponse:
        """Every result file as one zip (features_*.dds, decoder.bin, manifest.json, report.json, report.html,
        baselines/...)."""
        job = succeeded(job_id)
        folder = queue.artifacts_path(job.id)
        settings.uploads_dir.mkdir(parents=True, exist_ok=True)
        handle = tempfile.NamedTemporaryFile(dir=settings.uploads_dir, prefix="download-", suffix=".zip",
                                             delete=False)
        with handle, zipfile.ZipFile(handle, "w", zipfile.ZIP_DEFLATED) as archive:
            for name in job.result.artifacts if job.result else []:
                archive.write(folder / name, name)
        return FileResponse(handle.name, media_type="application/zip", filename=f"{job.name}-{job.id}.zip",
                            background=BackgroundTask(Path(handle.name).unlink, missing_ok=True))

    @app.get("/v1/jobs/{job_id}/artifacts/{name:path}", tags=["results"], dependencies=guarded,
             response_class=FileResponse)
    def get_artifact(job_id: str, name: str) -> FileResponse:
        """One result file by its name in the job's `result.artifacts`."""
        job = succeeded(job_id)
        if job.result is None or name not in job.result.artifacts:
            raise HTTPException(404, f"job {job.id} has no artifact {name!r}; it has "
                                     f"{', '.join(job.result.artifacts) if job.result else 'none'}")
        return FileResponse(queue.artifacts_path(job.id) / name, filename=Path(name).name)

    return app


def gated(app: FastAPI, settings: Settings) -> ASGIApp:
    """The app as uvicorn runs it: with the token check and the upload limit in front."""
    return RequestGate(app, settings)

