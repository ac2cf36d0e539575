"""The HTTP API (FastAPI): submit materials, follow jobs, fetch reports and artifacts; `bcf serve` runs
`gated(create_app(settings), settings)` with uvicorn, and workers do the compressing.

Routes only translate between HTTP and `bcf.jobs`: settings, queue, authorisation and the job a path names
come in as FastAPI dependencies; answers are filtered through the public `JobView`, never the stored record.
The token and the body size are checked before all that, in front of the app (`RequestGate`).
"""

from __future__ import annotations

import json
import secrets
from pathlib import Path
from typing import Annotated, Any, Callable, Literal, Optional

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, Field
from starlette.background import BackgroundTask
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Route
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from bcf.core import REPORT_FILE, Report, __version__
from bcf.jobs.queue import JobQueue
from bcf.jobs.records import DEFAULT_TENANT, FINAL_STATES, Job, JobState, JobView
from bcf.jobs.settings import Settings
from bcf.jobs.storage import ObjectStoreUnavailable
from bcf.jobs.store import StoreUnavailable, free_disk_bytes
from bcf.jobs.supervisor import WorkerStatus
from bcf.service.metrics import prometheus_text
from bcf.service.uploads import DiskFull, Upload, read_upload, submit_upload

__all__ = ["JobList", "create_app", "gated"]


# ---------------------------------------------------------------------------------------------- the gate

# Paths anyone may read: liveness, readiness and the API description.
OPEN_PATHS = frozenset({"/healthz", "/readyz", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"})
UNAUTHORISED = "missing or wrong bearer token (Authorization: Bearer <one of BCF_API_TOKENS>)"
MAX_LIST_OFFSET = 2**62  # the job store is SQLite: OFFSET is a signed 64-bit integer
# An artifact's media type by its suffix, stated rather than guessed from the platform's MIME table (which
# calls .dds an image on some systems and knows nothing of it on others); anything else is octet-stream.
ARTIFACT_TYPES = {".json": "application/json", ".html": "text/html"}
_BINARY = {"type": "string", "format": "binary"}
_ARTIFACT_CONTENT = {"application/json": {"schema": {}}, "text/html": {"schema": {"type": "string"}},
                     "application/octet-stream": {"schema": _BINARY}}


class _BodyTooLarge(Exception):
    pass


class Refusals(BaseModel):
    """Requests refused by this server process since it started, for /metrics (kept in `app.state`)."""

    disk: int = Field(0, description="uploads refused for lack of disk space (507)")


def disk_floor_message(settings: Settings, free: int, needed: int = 0) -> Optional[str]:
    """Why an upload of `needed` bytes is refused, if storing it would leave less than BCF_MIN_FREE_DISK_MB free."""
    floor = settings.min_free_disk_bytes
    if floor == 0 or free - needed >= floor:
        return None
    return (f"not enough disk space for the upload: {free / 2**20:.0f} MiB free on the data directory's disk"
            + (f", {needed / 2**20:.1f} MiB needed" if needed else "")
            + f", and {settings.min_free_disk_mb:.0f} MiB must stay free (BCF_MIN_FREE_DISK_MB); retry once "
              "jobs are purged (DELETE /v1/jobs/{id}?purge=true) or expire (BCF_RETENTION_DAYS)")


def token_accepted(given: str, tokens: list[str]) -> bool:
    """One of `tokens`, compared in constant time (the gate and the app's dependency both ask this)."""
    return any(secrets.compare_digest(given.encode(), t.encode()) for t in tokens)


async def _send_error(send: Send, status: int, detail: str, headers: Optional[list] = None) -> None:
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"connection", b"close"), *(headers or [])]})
    await send({"type": "http.response.body", "body": json.dumps({"detail": detail}).encode()})


class RequestGate:
    """The bearer token (401), then the body size (413) by Content-Length and by counting as it streams in
    (chunked uploads), and for uploads the free disk space (507, `disk_floor_message`). Here, not in a FastAPI
    dependency: FastAPI reads and parses a form before it runs any dependency."""

    def __init__(self, app: ASGIApp, settings: Settings, refusals: Optional[Refusals] = None):
        self.app = app
        self.settings = settings
        self.refusals = refusals or Refusals()
        self.tokens = list(settings.token_tenants())
        self.limit = int(settings.max_upload_mb * 2**20)
        self.too_large = f"request body larger than the limit of {settings.max_upload_mb:.0f} MiB (BCF_MAX_UPLOAD_MB)"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope["headers"])
        scheme, _, given = headers.get(b"authorization", b"").decode("latin-1").partition(" ")
        if (self.tokens and scope["path"] not in OPEN_PATHS
                and not (scheme.lower() == "bearer" and token_accepted(given, self.tokens))):
            await _send_error(send, 401, UNAUTHORISED, [(b"www-authenticate", b"Bearer")])
            return
        length = headers.get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.limit:
            await _send_error(send, 413, self.too_large)
            return
        if scope["method"] == "POST" and scope["path"] == "/v1/jobs":
            needed = int(length) if length is not None and length.isdigit() else 0
            refused = disk_floor_message(self.settings, free_disk_bytes(self.settings.data_dir), needed)
            if refused:
                self.refusals.disk += 1
                await _send_error(send, 507, refused)
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
                        await _send_error(send, 413, self.too_large)
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
                await _send_error(send, 413, self.too_large)


# ------------------------------------------------------------------------------------------- dependencies


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_queue(request: Request) -> JobQueue:
    return request.app.state.queue


def get_refusals(request: Request) -> Refusals:
    return request.app.state.refusals


def get_workers(request: Request) -> Optional[WorkerStatus]:
    """The supervised workers' status, or None where `bcf serve` starts none (farm mode: `bcf worker`s)."""
    status = request.app.state.workers
    return None if status is None else status()


SettingsDep = Annotated[Settings, Depends(get_settings)]
QueueDep = Annotated[JobQueue, Depends(get_queue)]
WorkersDep = Annotated[Optional[WorkerStatus], Depends(get_workers)]
RefusalsDep = Annotated[Refusals, Depends(get_refusals)]
_bearer = HTTPBearer(auto_error=False, description="one of BCF_API_TOKENS")


def authorised(settings: SettingsDep,
               credentials: Annotated[Optional[HTTPAuthorizationCredentials], Depends(_bearer)]) -> Optional[str]:
    """The caller's tenant (None: the admin token, or no tokens configured, when `bcf serve` listens on
    127.0.0.1 only and one user sees everything). Checked again here (`RequestGate` checks first) so the app
    is safe without the gate too, and so OpenAPI shows the bearer scheme."""
    tenants = settings.token_tenants()
    if not tenants:
        return None
    given = credentials.credentials if credentials else ""
    for token, tenant in tenants.items():
        if token_accepted(given, [token]):
            return tenant
    raise HTTPException(401, UNAUTHORISED, headers={"WWW-Authenticate": "Bearer"})


Tenant = Annotated[Optional[str], Depends(authorised)]


def stored_job(job_id: str, queue: QueueDep, tenant: Tenant) -> Job:
    """The job of the path; another tenant's job is as absent as one that never existed."""
    job = queue.store.get(job_id)
    if job is None or (tenant is not None and job.tenant != tenant):
        raise HTTPException(404, f"no job {job_id!r}")
    return job


StoredJob = Annotated[Job, Depends(stored_job)]


def succeeded_job(job: StoredJob) -> Job:
    """The job of the path, if it has results (409 before)."""
    if job.state != "succeeded":
        raise HTTPException(409, f"job {job.id} is {job.state}; results exist once it has succeeded"
                            + (f" (error: {job.error})" if job.error else ""))
    if job.purged_at is not None:
        raise HTTPException(410, f"job {job.id}'s files were removed at {job.purged_at.isoformat()} (purged, or "
                                 "older than BCF_RETENTION_DAYS); submit the material again to recompute them")
    return job


SucceededJob = Annotated[Job, Depends(succeeded_job)]


# ------------------------------------------------------------------------------------------------- routes


class JobList(BaseModel):
    jobs: list[JobView]
    total: int
    offset: int
    limit: int


class ErrorBody(BaseModel):
    """Every error the service sends: one message a build engineer can act on."""

    detail: str


_ERRORS = {400: "a malformed form: an unknown or repeated field, both a zip and role files, a zip entry that "
                "escapes the archive",
           401: "missing or wrong bearer token",
           404: "no such job, or no such artifact of the job",
           409: "the job is not in a state that allows this (results before it succeeded, cancelling a finished "
                "job, purging a running one)",
           410: "the job's files were removed (purged, or expired after BCF_RETENTION_DAYS); its record remains",
           413: "upload over BCF_MAX_UPLOAD_MB, or a material zip over BCF_MAX_UNZIPPED_MB",
           415: "a file is not an accepted image, or the material not a zip",
           422: "a parameter, the options or the material cannot be used",
           503: "the job store (or the object storage of BCF_STORAGE_URL) does not answer; retry after "
                "Retry-After seconds",
           507: "not enough disk space: the upload would leave less than BCF_MIN_FREE_DISK_MB free, or the disk "
                "filled while it was stored"}


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` for error codes, each with the one error body."""
    return {code: {"model": ErrorBody, "description": _ERRORS[code]} for code in codes}


open_routes = APIRouter(responses=_errors(503))
routes = APIRouter(dependencies=[Depends(authorised)], responses=_errors(401, 503))


@open_routes.get("/healthz", tags=["service"])
def healthz(settings: SettingsDep, queue: QueueDep) -> dict[str, str]:
    """Liveness and whether the job store answers (no token needed; 503 when it does not)."""
    queue.store.ping()
    return {"status": "ok", "version": __version__, "mode": "farm" if settings.farm_mode else "embedded"}


class Readiness(BaseModel):
    ready: bool
    store: Literal["ok", "unavailable"]
    disk: Literal["ok", "low"]  # low: less than BCF_MIN_FREE_DISK_MB free, uploads are refused
    disk_free_bytes: int  # on the data folder's file system
    workers: Optional[WorkerStatus]  # None where this server starts no workers (farm mode)


@open_routes.get("/readyz", tags=["service"], response_model=Readiness,
                 responses={503: {"model": Readiness, "description": "not ready: the job store does not answer, "
                                                                      "less than BCF_MIN_FREE_DISK_MB is free, "
                                                                      "or none of this server's workers runs"}})
def readyz(settings: SettingsDep, queue: QueueDep, workers: WorkersDep, response: Response) -> Readiness:
    """Readiness for an orchestrator (no token needed): the job store answers, the data directory's disk has
    BCF_MIN_FREE_DISK_MB free and, where this server supervises workers, at least one runs. 503 otherwise, with
    the same body."""
    try:
        queue.store.ping()
        store: Literal["ok", "unavailable"] = "ok"
    except StoreUnavailable:
        store = "unavailable"
    free = free_disk_bytes(settings.data_dir)
    disk: Literal["ok", "low"] = "low" if disk_floor_message(settings, free) else "ok"
    ready = store == "ok" and disk == "ok" and (workers is None or workers.live > 0)
    response.status_code = 200 if ready else 503
    return Readiness(ready=ready, store=store, disk=disk, disk_free_bytes=free, workers=workers)


@routes.get("/metrics", tags=["service"], response_class=PlainTextResponse)
def metrics(queue: QueueDep, workers: WorkersDep, refusals: RefusalsDep) -> PlainTextResponse:
    """Prometheus text format: jobs by state, purged jobs, queue depth, job durations, free disk space, uploads
    refused for disk space, supervised workers and restarts."""
    return PlainTextResponse(prometheus_text(queue, workers, refusals.disk), media_type="text/plain; version=0.0.4")


@routes.post("/v1/jobs", tags=["jobs"], status_code=202, response_model=JobView,
             responses={200: {"model": JobView,
                              "description": "the same inputs and options were submitted before: that job"},
                        **_errors(400, 413, 415, 422, 507)})
async def submit(upload: Annotated[Upload, Depends(read_upload)], queue: QueueDep, tenant: Tenant,
                 refusals: RefusalsDep, response: Response) -> Job:
    """Submit a material: files per role, or a zip. 202 with the new job, or 200 with the existing job when
    the same files and options were submitted before (and did not fail)."""
    try:
        job, created = await run_in_threadpool(submit_upload, queue, upload, tenant or DEFAULT_TENANT)
    except DiskFull as exc:
        refusals.disk += 1
        raise HTTPException(507, str(exc)) from None
    response.status_code, response.headers["Location"] = 202 if created else 200, f"/v1/jobs/{job.id}"
    return job


@routes.get("/v1/jobs", tags=["jobs"], responses=_errors(422))
def list_jobs(queue: QueueDep, tenant: Tenant,
              state: Annotated[Optional[list[JobState]], Query(description="repeat to give several")] = None,
              offset: Annotated[int, Query(ge=0, le=MAX_LIST_OFFSET)] = 0,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> JobList:
    """Jobs, newest first: the caller's tenant's (the admin token's: every tenant's)."""
    jobs, total = queue.store.list(set(state) if state else None, offset, limit, tenant)
    return JobList(jobs=jobs, total=total, offset=offset, limit=limit)


@routes.get("/v1/jobs/{job_id}", tags=["jobs"], response_model=JobView, responses=_errors(404, 422))
def get_job(job: StoredJob) -> Job:
    return job


@routes.delete("/v1/jobs/{job_id}", tags=["jobs"], response_model=JobView,
               responses={202: {"model": JobView, "description": "running: it stops within a heartbeat or two"},
                          **_errors(404, 409, 422)})
def cancel_job(job: StoredJob, queue: QueueDep, response: Response,
               purge: Annotated[bool, Query(description="also remove the job's inputs and result files, keeping "
                                                        "its record (a finished or queued job; not a running one)")
                                ] = False) -> Job:
    """Cancel: a queued job at once (200), a running one within a few seconds (202; watch its state). With
    `purge=true`: remove a finished (or queued: cancelled first) job's files, keeping the record (200)."""
    if purge and job.state == "running":
        raise HTTPException(409, f"job {job.id} is running; cancel it (DELETE without purge), then purge it once "
                                 "it is cancelled")
    if not (purge and job.state in FINAL_STATES):
        job = queue.cancel(job.id) or job  # None only for a job that vanished meanwhile: jobs are never deleted
        if job.state in FINAL_STATES and job.state != "cancelled":
            raise HTTPException(409, f"job {job.id} already {job.state}; nothing to cancel")
    if purge:
        job = queue.purge(job.id) or job
        if job.purged_at is None:  # a worker took it between the two steps: cancelling, not purged
            raise HTTPException(409, f"job {job.id} started running; it is being cancelled: purge it once it is "
                                     "cancelled")
    response.status_code = 200 if job.state in FINAL_STATES else 202
    return job


def _artifact_response(queue: JobQueue, job: Job, name: str, media_type: str,
                       filename: Optional[str] = None) -> Response:
    """A result file: from the data folder as a file, or streamed from object storage."""
    if not queue.storage.remote:
        return FileResponse(queue.artifacts_path(job.id) / name, media_type=media_type, filename=filename)
    try:
        body = queue.storage.open_artifact(job.id, name)
    except FileNotFoundError:
        raise HTTPException(404, f"job {job.id}'s artifact {name!r} is missing from object storage") from None
    headers = {"Content-Disposition": f'attachment; filename="{filename}"'} if filename else None
    return StreamingResponse(iter(lambda: body.read(2**20), b""), media_type=media_type, headers=headers,
                             background=BackgroundTask(body.close))


@routes.get("/v1/jobs/{job_id}/report", tags=["results"], response_class=FileResponse,
            responses={200: {"model": Report, "description": "report.json"}, **_errors(404, 409, 410, 422)})
def get_report(job: SucceededJob, queue: QueueDep) -> Response:
    """The job's report.json (the schema is in docs/FORMAT.md)."""
    return _artifact_response(queue, job, REPORT_FILE, "application/json")


@routes.get("/v1/jobs/{job_id}/artifacts", tags=["results"], response_class=FileResponse,
            responses={200: {"content": {"application/zip": {"schema": _BINARY}}, "description": "a zip"},
                       **_errors(404, 409, 410, 422)})
def get_artifacts(job: SucceededJob, queue: QueueDep, settings: SettingsDep) -> FileResponse:
    """Every result file as one zip (features_*.dds, decoder.bin, manifest.json, report.json, report.html,
    baselines/...)."""
    archive = queue.pack_artifacts(job, settings.uploads_dir)
    return FileResponse(archive, media_type="application/zip", filename=f"{job.name}-{job.id}.zip",
                        background=BackgroundTask(archive.unlink, missing_ok=True))


@routes.get("/v1/jobs/{job_id}/artifacts/{name:path}", tags=["results"], response_class=FileResponse,
            responses={200: {"content": _ARTIFACT_CONTENT,
                             "description": "the file: JSON, HTML, or binary (DDS, KTX2, ASTC, decoder.bin)"},
                       **_errors(404, 409, 410, 422)})
def get_artifact(job: SucceededJob, name: str, queue: QueueDep) -> Response:
    """One result file by its name in the job's `result.artifacts`."""
    artifacts = job.result.artifacts if job.result else []
    if name not in artifacts:
        raise HTTPException(404, f"job {job.id} has no artifact {name!r}; it has {', '.join(artifacts) or 'none'}")
    return _artifact_response(queue, job, name, ARTIFACT_TYPES.get(Path(name).suffix.lower(),
                                                                   "application/octet-stream"), Path(name).name)


# ------------------------------------------------------------------------------------------ the application


async def _store_down(request: Request, exc: StoreUnavailable) -> JSONResponse:
    what = "object storage" if isinstance(exc, ObjectStoreUnavailable) else "job store"
    return JSONResponse({"detail": f"{what} unavailable, retry later: {exc}"}, status_code=503,
                        headers={"Retry-After": "5"})


async def _method_not_allowed(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    """405 with every method of the path in `Allow`: FastAPI makes one route per method, and Starlette's own
    answer names only the methods of the first route whose path matches."""
    candidates = [*request.app.router.routes, *open_routes.routes, *routes.routes]  # the app's own: /openapi.json
    methods = {method for route in candidates if isinstance(route, Route) and route.path_regex.match(request.url.path)
               for method in route.methods or ()}
    return JSONResponse({"detail": exc.detail}, status_code=405, headers={"Allow": ", ".join(sorted(methods))})


async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
    problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
    return JSONResponse({"detail": problems}, status_code=422)


def create_app(settings: Settings, workers: Optional[Callable[[], WorkerStatus]] = None) -> FastAPI:
    """The API over the job queue `settings` describe; both live in `app.state`, for the dependencies, with
    `workers`, the status of the workers `bcf serve` supervises (None: it runs none)."""
    app = FastAPI(title="bcf", version=__version__,
                  description="Neural block-compressed features (BC6H) for PBR materials: submit a texture set, "
                              "get BC6H feature textures, MLP weights and a quality report.")
    app.state.settings, app.state.queue, app.state.workers = settings, JobQueue(settings), workers
    app.state.refusals = Refusals()
    app.add_exception_handler(StoreUnavailable, _store_down)  # type: ignore[arg-type]  # and ObjectStoreUnavailable
    app.add_exception_handler(RequestValidationError, _invalid)  # type: ignore[arg-type]
    app.add_exception_handler(405, _method_not_allowed)  # type: ignore[arg-type]
    app.include_router(open_routes)
    app.include_router(routes)
    app.openapi = lambda: _errors_as_json(app)  # type: ignore[method-assign]
    return app


def _errors_as_json(app: FastAPI) -> dict[str, Any]:
    """The OpenAPI document, with every error body under application/json: FastAPI files an operation's error
    responses under its success media type (text/plain for /metrics), but errors are always JSON."""
    if app.openapi_schema is None:
        document = FastAPI.openapi(app)
        for operations in document["paths"].values():
            for operation in operations.values():
                for code, response in operation.get("responses", {}).items():
                    bodies = [c["schema"] for c in response.get("content", {}).values() if "schema" in c]
                    if int(code) >= 400 and bodies:
                        response["content"] = {"application/json": {"schema": bodies[0]}}
        _forms_as_sent(document)
        app.openapi_schema = document
    return app.openapi_schema


def _forms_as_sent(document: dict[str, Any]) -> None:
    """Multipart forms as clients can send them: FastAPI writes an optional field as "the value or null", but
    a form has no null (a field left out is how it is omitted; a text part named like a file field is not a
    file), and a field the form does not name is a 400 (`read_upload`), so the form admits no others."""
    forms = [operation["requestBody"]["content"]["multipart/form-data"]["schema"]
             for operations in document["paths"].values() for operation in operations.values()
             if "multipart/form-data" in operation.get("requestBody", {}).get("content", {})]
    for reference in forms:
        form = document["components"]["schemas"][reference["$ref"].rpartition("/")[2]]
        for name, field in form["properties"].items():
            kinds = [kind for kind in field.pop("anyOf", []) if kind != {"type": "null"}]
            form["properties"][name] = {**kinds[0], **field} if len(kinds) == 1 else field
        form["additionalProperties"] = False


def gated(app: FastAPI, settings: Settings) -> ASGIApp:
    """The app as uvicorn runs it: with the token check, the upload limit and the disk floor in front
    (`RequestGate`), counting its refusals where the app's /metrics reads them."""
    return RequestGate(app, settings, app.state.refusals)
