"""Service and worker settings, read from the environment (prefix BCF_) and an optional `.env` file.

One `Settings` object is built per process (`Settings()`) and passed down; nothing reads the environment
after that, so tests and embedded workers can run with their own settings side by side.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from bcf.core import MAX_TEXTURE_PIXELS, physical_memory
from bcf.jobs.records import DEFAULT_TENANT

__all__ = ["Settings"]


class Settings(BaseSettings):
    """Every setting of `bcf serve` and `bcf worker`; environment variable = BCF_ + the name in capitals."""

    model_config = SettingsConfigDict(env_prefix="BCF_", env_file=".env", extra="ignore")

    data_dir: Path = Field(default_factory=lambda: Path.home() / ".local" / "share" / "bcf",
                           description="queue and job databases (embedded mode), uploaded inputs, artifacts")
    api_tokens: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="comma-separated bearer tokens, each tenant:token (its jobs are the "
        "tenant's: other tenants cannot see them) or a bare token (tenant default); none: the API listens on "
        "127.0.0.1 only")
    admin_token: Optional[str] = Field(None, description="a bearer token that sees and manages every tenant's jobs")
    queue_url: Optional[str] = Field(None, description="redis://host:port/db: farm mode with Redis; "
                                                       "unset: embedded mode with SQLite files in data_dir")
    max_upload_mb: float = Field(512.0, gt=0, description="largest accepted request body, in MiB")
    max_unzipped_mb: float = Field(2048.0, gt=0, description="largest total size of a material zip's entries")
    max_zip_entries: int = Field(64, ge=1, description="most entries a material zip may have")
    max_texture_pixels: int = Field(
        MAX_TEXTURE_PIXELS, ge=64 * 64, le=16384 * 16384,
        description="largest texture accepted, width x height, checked from each image's header before any pixel "
                    "is decoded (the default allows 8K textures)")
    job_memory_mb: Optional[float] = Field(
        None, gt=0, description="largest estimated peak memory of one job, in MiB, checked from the image headers "
        "before any pixel is decoded (at submission and again by the worker); none: the physical memory of the "
        "machine that checks")
    job_time_limit_s: float = Field(86400.0, gt=0, description="wall-clock limit of one job's run, in seconds: "
                                    "a job still running then stops and fails")
    max_attempts: int = Field(3, ge=1, description="runs of a job before a worker death marks it failed")
    heartbeat_s: float = Field(2.0, gt=0, description="how often a running job's record is refreshed")
    stale_after_s: float = Field(30.0, gt=0, description="a running job whose record is this old has lost "
                                                         "its worker and is re-queued")
    min_free_disk_mb: float = Field(1024.0, ge=0, description="free space (MiB) the data directory's disk keeps: "
                                    "uploads that would leave less are refused with 507 and /readyz is not ready; "
                                    "0: no floor")
    retention_days: Optional[float] = Field(None, gt=0, description="days a finished job keeps its inputs and "
                                            "results; then its files are removed and the record kept as a "
                                            "tombstone; none: kept until purged")

    storage_url: Optional[str] = Field(
        None, description="s3://bucket/prefix: uploaded inputs and job results in S3-compatible object storage "
        "(credentials and endpoint from the standard AWS_* variables), and BCF_DATA_DIR is scratch; none: "
        "they live in BCF_DATA_DIR, which every worker must mount")
    storage_timeout_s: float = Field(30.0, gt=0, description="connect and read timeout of one object storage "
                                     "request, in seconds")
    storage_retries: int = Field(4, ge=1, description="tries of one object storage request (botocore's standard "
                                 "retries, with backoff) before the job's attempt fails")
    callback_secret: Optional[str] = Field(None, description="key of the HMAC-SHA256 signature of job callbacks "
                                           "(X-Bcf-Signature header); none: callbacks are sent unsigned")
    callback_attempts: int = Field(5, ge=1, description="tries of one job callback POST, with exponential "
                                   "backoff, before it is given up (logged)")

    @field_validator("api_tokens", mode="before")
    @classmethod
    def _split_tokens(cls, value: object) -> object:
        if isinstance(value, str):
            return [token.strip() for token in value.split(",") if token.strip()]
        return value

    @field_validator("queue_url")
    @classmethod
    def _redis_only(cls, value: Optional[str]) -> Optional[str]:
        if value is not None and not value.strip():
            return None
        if value is not None and not value.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError(f"BCF_QUEUE_URL must be a redis://, rediss:// or unix:// URL, got {value!r}")
        return value

    @field_validator("storage_url")
    @classmethod
    def _s3_only(cls, value: Optional[str]) -> Optional[str]:
        if value is not None and not value.strip():
            return None
        if value is not None and (not value.startswith("s3://") or not value.removeprefix("s3://").split("/")[0]):
            raise ValueError(f"BCF_STORAGE_URL must be an s3://bucket/prefix URL, got {value!r}")
        return value

    @field_validator("api_tokens")
    @classmethod
    def _tenant_names(cls, value: list[str]) -> list[str]:
        for entry in value:
            tenant, separator, token = entry.rpartition(":")
            if separator and (not tenant or not token):
                raise ValueError(f"BCF_API_TOKENS: {entry!r} is not tenant:token")
        return value

    def token_tenants(self) -> dict[str, Optional[str]]:
        """Every accepted bearer token -> its tenant; the admin token -> None (every tenant)."""
        tenants: dict[str, Optional[str]] = {}
        for entry in self.api_tokens:
            tenant, separator, token = entry.rpartition(":")
            tenants[token] = tenant if separator else DEFAULT_TENANT
        if self.admin_token:
            tenants[self.admin_token] = None
        return tenants

    def memory_budget(self) -> int:
        """Bytes a job may need (`job_memory_mb`, else this machine's physical memory)."""
        return int(self.job_memory_mb * 2**20) if self.job_memory_mb else physical_memory()

    @property
    def farm_mode(self) -> bool:
        return self.queue_url is not None

    @property
    def min_free_disk_bytes(self) -> int:
        return int(self.min_free_disk_mb * 2**20)

    @property
    def uploads_dir(self) -> Path:
        """Staging of requests being validated and of downloads, each removed once answered."""
        return self.data_dir / "uploads"
