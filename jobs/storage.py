"""Where a job's inputs and result files live between machines: `BCF_STORAGE_URL`.

`LocalStorage` (the default) is the data folder itself: submission renames the inputs into `inputs/<id>/`, a
worker writes the result into `artifacts/<id>/`, and every process mounts the same folder. `S3Storage` keeps
them in S3-compatible object storage (AWS S3, MinIO, Ceph, ...) under `s3://bucket/prefix`, so workers need no
shared file system: their `BCF_DATA_DIR` is only scratch space. The queue calls the same few methods either
way; for `LocalStorage` most are no-ops, because the files are already where they belong.

S3 has no rename, so a result is committed by its marker: a worker uploads every file of one attempt under
`artifacts/<id>/<attempt>/...`, then writes `artifacts/<id>/COMMITTED.json` (the succeeded record and the
attempt) last. Readers trust only the committed attempt: a worker killed mid-upload leaves objects no reader
looks at, removed by the next attempt or a purge. Credentials and the endpoint come from the standard AWS
variables (AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_ENDPOINT_URL or AWS_ENDPOINT_URL_S3,
AWS_DEFAULT_REGION); botocore retries transient errors, and what still fails is a `ObjectStoreUnavailable`.
"""

from __future__ import annotations

import shutil
import uuid
from pathlib import Path
from typing import IO, Any, Callable, Optional, Protocol

from pydantic import BaseModel, ValidationError

from bcf.jobs.records import RECORD_FILE, Job, read_record
from bcf.jobs.settings import Settings
from bcf.jobs.store import StoreUnavailable

__all__ = ["COMMIT_MARKER", "JobStorage", "LocalStorage", "S3Storage", "ObjectStoreUnavailable", "open_storage"]

COMMIT_MARKER = "COMMITTED.json"


class ObjectStoreUnavailable(StoreUnavailable):
    """The object store did not answer, or refused, after botocore's retries: the job's attempt fails and is
    retried (`BCF_MAX_ATTEMPTS`). A kind of `StoreUnavailable`, so that what retries or reports a job store
    that does not answer (recovery passes, `bcf admin recover`) does the same for it."""


class Committed(BaseModel):
    """The commit marker of a result in object storage: which attempt's objects make it, and its record."""

    attempt: str
    job: Job


class JobStorage(Protocol):
    """Inputs and results of jobs, as the queue, the workers and the API use them. `folder` arguments are the
    job's local folders (`JobQueue.inputs_path`, `artifacts_path`)."""

    remote: bool  # False: the data folder is the storage (shared by every process); True: it is scratch

    def put_inputs(self, job_id: str, folder: Path) -> None:
        """Store the input files of a new job (before it is queued)."""

    def fetch_inputs(self, job_id: str, folder: Path) -> None:
        """The job's input files into `folder`, for a worker."""

    def remove_inputs(self, job_id: str) -> None:
        """Remove a finished job's input files from the storage (its record stays)."""

    def put_record(self, job_id: str, job: Job) -> None:
        """The job's record beside its stored inputs."""

    def job_ids(self) -> set[str]:
        """Ids of the jobs the storage holds inputs or results of (for a rebuild of lost records)."""

    def record(self, job_id: str) -> Optional[Job]:
        """The record kept beside the job's stored inputs, if there is a readable one."""

    def put_artifacts(self, job_id: str, folder: Path, record: Job) -> None:
        """Commit the files `record.result.artifacts` in `folder` as the job's result, all or nothing."""

    def finished_record(self, job_id: str) -> Optional[Job]:
        """The committed succeeded record, if the storage holds the complete result."""

    def open_artifact(self, job_id: str, name: str) -> IO[bytes]:
        """A committed result file, to read (FileNotFoundError if missing)."""

    def remove_artifacts(self, job_id: str) -> None:
        """Remove every object or file of the job's result, committed or not."""


class LocalStorage:
    """The data folder as the storage: today's layout, with nothing to copy."""

    remote = False

    def __init__(self, settings: Settings):
        self.data_dir = settings.data_dir

    def put_inputs(self, job_id: str, folder: Path) -> None:
        pass  # the submitter renamed them into place

    def fetch_inputs(self, job_id: str, folder: Path) -> None:
        pass  # every worker mounts the same folder

    def remove_inputs(self, job_id: str) -> None:
        pass  # the queue removes local input files itself

    def put_record(self, job_id: str, job: Job) -> None:
        pass  # the queue writes it into the inputs folder

    def job_ids(self) -> set[str]:
        return set()  # the rebuild scans the data folder itself

    def record(self, job_id: str) -> Optional[Job]:
        return None  # the rebuild reads the data folder's job.json itself

    def put_artifacts(self, job_id: str, folder: Path, record: Job) -> None:
        pass  # the result was staged and renamed into place by `compress_material`; its job.json marks it

    def finished_record(self, job_id: str) -> Optional[Job]:
        folder = self.data_dir / "artifacts" / job_id
        job = read_record(folder)
        if job is None or job.state != "succeeded" or job.result is None:
            return None
        return job if all((folder / name).is_file() for name in job.result.artifacts) else None

    def open_artifact(self, job_id: str, name: str) -> IO[bytes]:
        return (self.data_dir / "artifacts" / job_id / name).open("rb")

    def remove_artifacts(self, job_id: str) -> None:
        shutil.rmtree(self.data_dir / "artifacts" / job_id, ignore_errors=True)


class S3Storage:
    """S3-compatible object storage under `s3://bucket/prefix` (boto3)."""

    remote = True

    def __init__(self, settings: Settings):
        import boto3  # only processes configured for S3 pay for importing it
        from botocore.config import Config

        url = settings.storage_url or ""
        self.url = url
        self.bucket, _, prefix = url.removeprefix("s3://").partition("/")
        self.prefix = prefix.strip("/")
        timeout = settings.storage_timeout_s
        # botocore retries throttling, 5xx answers and dropped connections itself ("standard" mode, with
        # backoff); what fails after that fails the job's attempt.
        config = Config(connect_timeout=timeout, read_timeout=timeout,
                        retries={"max_attempts": settings.storage_retries, "mode": "standard"})
        self.client = boto3.client("s3", config=config)

    def _key(self, *parts: str) -> str:
        return "/".join(p for p in (self.prefix, *parts) if p)

    def _call(self, what: str, call: Callable[..., Any], *args: object, **kwargs: object) -> Any:
        """`call(*args, **kwargs)`; a missing object is FileNotFoundError, any other failure (after botocore's
        retries) ObjectStoreUnavailable naming the store and what was being done."""
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            return call(*args, **kwargs)
        except ClientError as exc:
            if exc.response.get("Error", {}).get("Code") in ("NoSuchKey", "404"):
                raise FileNotFoundError(what) from exc
            raise ObjectStoreUnavailable(f"object storage {self.url}: {what}: {exc}") from exc
        except BotoCoreError as exc:
            raise ObjectStoreUnavailable(f"object storage {self.url}: {what}: {exc}") from exc

    def _upload_folder(self, folder: Path, names: list[str], *key: str) -> None:
        for name in names:
            self._call(f"upload of {name}", self.client.upload_file, str(folder / name), self.bucket,
                       self._key(*key, name))

    def _keys(self, *key: str) -> list[str]:
        prefix = self._key(*key) + "/"
        paginator = self.client.get_paginator("list_objects_v2")
        pages = self._call("listing", lambda: list(paginator.paginate(Bucket=self.bucket, Prefix=prefix)))
        return [item["Key"] for page in pages for item in page.get("Contents", [])]

    def _delete(self, keys: list[str]) -> None:
        for start in range(0, len(keys), 1000):  # DeleteObjects takes at most 1000 keys
            batch = [{"Key": key} for key in keys[start:start + 1000]]
            self._call("removal", self.client.delete_objects, Bucket=self.bucket,
                       Delete={"Objects": batch, "Quiet": True})

    def put_inputs(self, job_id: str, folder: Path) -> None:
        names = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file() and p.name != RECORD_FILE)
        self._upload_folder(folder, names, "inputs", job_id)

    def fetch_inputs(self, job_id: str, folder: Path) -> None:
        shutil.rmtree(folder, ignore_errors=True)
        base = self._key("inputs", job_id) + "/"
        for key in self._keys("inputs", job_id):
            target = folder / key.removeprefix(base)
            target.parent.mkdir(parents=True, exist_ok=True)
            self._call(f"download of {target.name}", self.client.download_file, self.bucket, key, str(target))

    def remove_inputs(self, job_id: str) -> None:
        self._delete([k for k in self._keys("inputs", job_id) if not k.endswith("/" + RECORD_FILE)])

    def put_record(self, job_id: str, job: Job) -> None:
        self._call("record", self.client.put_object, Bucket=self.bucket, Key=self._key("inputs", job_id, RECORD_FILE),
                   Body=job.model_dump_json(indent=1).encode(), ContentType="application/json")

    def job_ids(self) -> set[str]:
        ids: set[str] = set()
        paginator = self.client.get_paginator("list_objects_v2")
        for kind in ("inputs", "artifacts"):
            prefix = self._key(kind) + "/"
            pages = self._call("listing", lambda: list(paginator.paginate(Bucket=self.bucket, Prefix=prefix,
                                                                          Delimiter="/")))
            ids |= {common["Prefix"][len(prefix):].strip("/") for page in pages
                    for common in page.get("CommonPrefixes", [])}
        return ids

    def record(self, job_id: str) -> Optional[Job]:
        try:
            body = self._call("record", self.client.get_object, Bucket=self.bucket,
                              Key=self._key("inputs", job_id, RECORD_FILE))["Body"].read()
            job = Job.model_validate_json(body)
        except (FileNotFoundError, ValidationError, ValueError):
            return None
        return job if job.id == job_id else None

    def put_artifacts(self, job_id: str, folder: Path, record: Job) -> None:
        attempt = f"attempt-{uuid.uuid4().hex[:12]}"
        names = record.result.artifacts if record.result else []
        self._upload_folder(folder, names, "artifacts", job_id, attempt)
        # The marker last: until this one PUT lands, readers see no result (S3 writes an object whole or not).
        marker = Committed(attempt=attempt, job=record).model_dump_json(indent=1).encode()
        self._call("commit", self.client.put_object, Bucket=self.bucket,
                   Key=self._key("artifacts", job_id, COMMIT_MARKER), Body=marker, ContentType="application/json")
        # Objects of attempts that never committed (a worker killed mid-upload): nobody reads them.
        keep = self._key("artifacts", job_id, attempt) + "/"
        marker_key = self._key("artifacts", job_id, COMMIT_MARKER)
        self._delete([k for k in self._keys("artifacts", job_id) if not k.startswith(keep) and k != marker_key])

    def _committed(self, job_id: str) -> Optional[Committed]:
        try:
            body = self._call("commit marker", self.client.get_object, Bucket=self.bucket,
                              Key=self._key("artifacts", job_id, COMMIT_MARKER))["Body"].read()
        except FileNotFoundError:
            return None
        try:
            return Committed.model_validate_json(body)
        except ValidationError:
            return None

    def finished_record(self, job_id: str) -> Optional[Job]:
        committed = self._committed(job_id)
        if committed is None or committed.job.id != job_id or committed.job.state != "succeeded":
            return None
        return committed.job

    def open_artifact(self, job_id: str, name: str) -> IO[bytes]:
        committed = self._committed(job_id)
        if committed is None:
            raise FileNotFoundError(name)
        answer = self._call(f"download of {name}", self.client.get_object, Bucket=self.bucket,
                            Key=self._key("artifacts", job_id, committed.attempt, name))
        return answer["Body"]

    def remove_artifacts(self, job_id: str) -> None:
        keys = self._keys("artifacts", job_id)
        marker = self._key("artifacts", job_id, COMMIT_MARKER)
        if marker in keys:  # the marker first: no reader follows it to objects being removed
            self._delete([marker])
        self._delete([k for k in keys if k != marker])


def open_storage(settings: Settings) -> JobStorage:
    """The storage `settings.storage_url` names: S3 for s3://..., else the data folder."""
    return S3Storage(settings) if settings.storage_url else LocalStorage(settings)
