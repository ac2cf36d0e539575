"""The stored job record: what the submitter creates, workers update and the stores keep (as JSON).

It holds bookkeeping clients do not need (attempts, the worker, the input key, stored paths); the HTTP service
answers with a public view of it instead."""

from __future__ import annotations

import datetime
import logging
from pathlib import Path
from typing import Literal, Optional, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from bcf.core import JobOptions, Role, write_text_atomic

__all__ = ["DEFAULT_TENANT", "FINAL_STATES", "JOB_STATES", "InputFile", "InputView", "Job", "JobProgress", "JobResult", "JobState",
           "JobView", "RECORD_FILE", "read_record", "utc_now", "write_record"]

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JOB_STATES: tuple[JobState, ...] = get_args(JobState)
FINAL_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})
RECORD_FILE = "job.json"  # a job's record kept beside its inputs and results (bcf.jobs.recovery)
log = logging.getLogger("bcf.jobs")
DEFAULT_TENANT = "default"  # the owner of jobs submitted with a bare token, or with none (loopback only)


def utc_now() -> datetime.datetime:
    return datetime.datetime.now(datetime.timezone.utc)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class JobProgress(_Model):
    """Where a job is. `phase`/`iteration`/`total` are the training phase's (1 or 2); `psnr` is the running
    training PSNR in dB; `eta_s` the training time left (both phases), null before the first estimate."""

    stage: str = Field("queued", description="queued, loading, training, evaluating, ... finished")
    phase: Optional[int] = None
    iteration: int = 0
    total: int = 0
    psnr: Optional[float] = None
    eta_s: Optional[float] = None


class InputView(BaseModel):
    """An input file as clients see it."""

    role: Role
    name: str = Field(description="the file name the client sent")
    sha256: str
    bytes: int


class InputFile(InputView, _Model):
    stored_as: str = Field(description="path in the job's inputs folder: <role>/<sanitised file name>")


class JobResult(_Model):
    """Headline numbers of a succeeded job (the full report is GET /v1/jobs/{id}/report)."""

    psnr: float = Field(description="aggregate PSNR over all mips and textures, dB")
    ssim: float
    size_bytes: int = Field(description="BC6H feature textures + decoder weights")
    bits_per_texel: float
    artifacts: list[str] = Field(description="files of the result, relative to the artifact folder")


class JobView(BaseModel):
    """A job as its submitter sees it (the HTTP API's job object). Unknown fields are ignored, so a client
    reads a newer server's answers; the stored `Job` adds the bookkeeping no client needs."""

    id: str
    state: JobState = "queued"
    name: str = Field(description="material name (zip folder or albedo file stem, sanitised)")
    options: JobOptions = Field(description="as submitted, with the normal convention the material was loaded with")
    inputs: list[InputView]
    notes: list[str] = Field(default_factory=list, description="what loading the material noticed (assumed "
                             "normal convention, ignored channels, constants used for missing maps)")
    progress: JobProgress = Field(default_factory=JobProgress)
    error: Optional[str] = None
    created_at: datetime.datetime = Field(default_factory=utc_now)
    updated_at: datetime.datetime = Field(default_factory=utc_now)
    started_at: Optional[datetime.datetime] = None
    finished_at: Optional[datetime.datetime] = None
    result: Optional[JobResult] = None
    purged_at: Optional[datetime.datetime] = Field(
        None, description="when the job's inputs and result files were removed (DELETE /v1/jobs/{id}?purge=true, "
                          "or BCF_RETENTION_DAYS after it finished); the record stays as a tombstone")


class Job(JobView, _Model):
    """The stored record: the public view and the bookkeeping of the queue, the workers and the inputs."""

    inputs: list[InputFile]
    input_key: str = Field(description="SHA-256 of the tenant, input files and options: equal keys are the same job")
    # Records written before tenants existed belong to the default one.
    tenant: str = Field(DEFAULT_TENANT, description="who submitted it: the name of its API token (BCF_API_TOKENS)")
    attempts: int = Field(0, description="times a worker started the job")
    worker: Optional[str] = None
    cancel_requested: bool = False
    # Not shown back: a receiver's URL may carry a token of its own.
    callback_url: Optional[str] = Field(None, description="where the job object is POSTed when the job ends "
                                        "(signed with BCF_CALLBACK_SECRET; docs/SERVICE.md, Callbacks)")
    heartbeat_at: Optional[datetime.datetime] = None

    def ended(self, state: JobState, last: Optional[JobProgress] = None, **fields: object) -> "Job":
        """The job finished in `state`, with its progress (`last` known, else as stored) saying so."""
        stage, eta = ("finished", 0.0) if state == "succeeded" else (state, None)
        progress = (last or self.progress).model_copy(update={"stage": stage, "eta_s": eta})
        return self.model_copy(update={"state": state, "finished_at": utc_now(), "progress": progress, **fields})

    def requeued(self) -> "Job":
        """Back in the queue for any worker: its worker stopped, died or gave it back."""
        return self.model_copy(update={"state": "queued", "worker": None, "started_at": None, "error": None,
                                       "progress": JobProgress(stage="queued")})

    def tombstone(self) -> "Job":
        """The record of a finished job whose files are removed: headline numbers kept, no artifacts listed."""
        result = self.result.model_copy(update={"artifacts": []}) if self.result else None
        return self.model_copy(update={"purged_at": utc_now(), "result": result})

    @property
    def duration_s(self) -> Optional[float]:
        if self.started_at is None or self.finished_at is None:
            return None
        return (self.finished_at - self.started_at).total_seconds()


# ------------------------------------------------------------------------------- the record as a file


def write_record(folder: Path, job: Job) -> bool:
    """`job` as `folder/job.json`, written atomically, if `folder` exists; False (and a warning) if it cannot be:
    the store still has the record, this is its copy."""
    if not folder.is_dir():
        return False
    try:
        write_text_atomic(folder / RECORD_FILE, job.model_dump_json(indent=1))
    except OSError as exc:
        log.warning("job %s: its record could not be kept in %s: %s", job.id, folder, exc)
        return False
    return True


def read_record(folder: Path) -> Optional[Job]:
    """The record in `folder/job.json`, if there is a readable one of the job the folder is named after."""
    try:
        job = Job.model_validate_json((folder / RECORD_FILE).read_bytes())
    except FileNotFoundError:
        return None
    except (OSError, ValidationError, ValueError) as exc:
        log.warning("%s: unreadable job record: %s", folder / RECORD_FILE, exc)
        return None
    return job if job.id == folder.name else None
