"""The job record: what the API returns, what workers update, what the stores keep (as JSON)."""

from __future__ import annotations

import datetime
import hashlib
import json
from typing import Literal, Optional, Sequence, get_args

from pydantic import BaseModel, ConfigDict, Field

from bcf.core import JobOptions, ResultIdentity

__all__ = ["FINAL_STATES", "JOB_STATES", "InputFile", "Job", "JobProgress", "JobResult", "JobState", "input_key",
           "utc_now"]

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JOB_STATES: tuple[JobState, ...] = get_args(JobState)
FINAL_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})


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


class InputFile(_Model):
    role: str
    name: str = Field(description="the file name the client sent (for display only; stored as <role>.<ext>)")
    stored_as: str
    sha256: str
    bytes: int


class JobResult(_Model):
    """Headline numbers of a succeeded job (the full report is GET /v1/jobs/{id}/report)."""

    psnr: float = Field(description="aggregate PSNR over all mips and textures, dB")
    ssim: float
    size_bytes: int = Field(description="BC6H feature textures + decoder weights")
    bits_per_texel: float
    artifacts: list[str] = Field(description="files of the result, relative to the artifact folder")


class Job(_Model):
    id: str
    state: JobState = "queued"
    name: str = Field(description="material name (zip folder or albedo file stem, sanitised)")
    options: JobOptions
    inputs: list[InputFile]
    input_key: str = Field(description="SHA-256 of the input files and options: equal keys are the same job")
    notes: list[str] = Field(default_factory=list, description="what loading the material noticed (assumed "
                             "normal convention, ignored channels, constants used for missing maps)")
    progress: JobProgress = Field(default_factory=JobProgress)
    error: Optional[str] = None
    attempts: int = Field(0, description="times a worker started the job")
    worker: Optional[str] = None
    cancel_requested: bool = False
    created_at: datetime.datetime = Field(default_factory=utc_now)
    updated_at: datetime.datetime = Field(default_factory=utc_now)
    started_at: Optional[datetime.datetime] = None
    heartbeat_at: Optional[datetime.datetime] = None
    finished_at: Optional[datetime.datetime] = None
    result: Optional[JobResult] = None

    @property
    def duration_s(self) -> Optional[float]:
        if self.started_at is None or self.finished_at is None:
            return None
        return (self.finished_at - self.started_at).total_seconds()


def input_key(identity: ResultIdentity, baselines: Sequence[str]) -> str:
    """Content hash that identifies a job: what decides its result (`bcf.core.result_identity`: the inputs' bytes
    by role, the normal convention and size they were loaded with, the resolved options without the device)
    and the baselines asked for. The name is left out."""
    keyed = {"result": identity.key(), "baselines": sorted(baselines)}
    return hashlib.sha256(json.dumps(keyed, sort_keys=True).encode()).hexdigest()
