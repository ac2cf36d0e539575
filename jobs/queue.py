"""The job queue: job records in a `JobStore` plus Huey messages that tell workers which job to run.

Huey carries only job ids; the record is the truth. A worker claims a job by moving it from queued to
running in the store, so a duplicate message (a re-queue racing a slow worker) is a no-op. Jobs are never
lost: the store persists them (SQLite file or Redis), Huey persists its messages, and `recover` re-queues
jobs whose worker stopped sending heartbeats and queued jobs whose message is missing. Each record is also kept
as a file beside the job's inputs and results (`bcf.jobs.recovery`), from which a lost store is rebuilt.
"""

from __future__ import annotations

import datetime
import logging
import shutil
import sqlite3
import tempfile
import zipfile
from pathlib import Path
from typing import Callable, Optional

from huey import Huey, RedisHuey, SqliteHuey

from bcf.core import staging_leftovers
from bcf.jobs.callbacks import send_callback
from bcf.jobs.records import FINAL_STATES, RECORD_FILE, Job, utc_now, write_record
from bcf.jobs.recovery import RecoveryReport, finished_record, rebuild_records
from bcf.jobs.settings import Settings
from bcf.jobs.storage import JobStorage, ObjectStoreUnavailable, open_storage
from bcf.jobs.store import JobStore, StoreUnavailable, open_store, sqlite_failure

__all__ = ["JobQueue", "RUN_JOB_TASK"]

RUN_JOB_TASK = "bcf.run_job"
JobRunner = Callable[[str], None]
log = logging.getLogger("bcf.jobs")


def _submitting_only(job_id: str) -> None:
    raise RuntimeError("this process only submits jobs; run them with 'bcf worker'")


class JobQueue:
    """Submit, cancel and recover jobs. `runner` is the function a worker runs for a job id (None in the API)."""

    def __init__(self, settings: Settings, runner: Optional[JobRunner] = None):
        self.settings = settings
        # RedisHuey on BCF_QUEUE_URL, else SqliteHuey in the data directory; no result store: results are files.
        if settings.queue_url:
            self.huey: Huey = RedisHuey("bcf", url=settings.queue_url, results=False)
        else:
            settings.data_dir.mkdir(parents=True, exist_ok=True)
            self.huey = SqliteHuey("bcf", filename=str(settings.data_dir / "queue.db"), results=False)
        self.storage: JobStorage = open_storage(settings)  # inputs and results: the data folder, or S3
        run = runner or _submitting_only

        def run_job(job_id: str) -> None:
            run(job_id)

        # Huey names a task after its function's module as well as `name`: the submitter's and the workers'
        # functions must share both, or workers find no task for the API's messages (only recovery re-sent them).
        self._task = self.huey.task(name=RUN_JOB_TASK)(run_job)
        # After the queue, so that a rebuild (which may re-queue jobs) can run from the store's first operation.
        self.store: JobStore = open_store(settings, on_recreated=self.rebuild)

    def enqueue(self, job_id: str) -> None:
        """Send the job's message; StoreUnavailable (StoreFull: its disk is full) if the SQLite queue fails."""
        try:
            self._task(job_id)
        except sqlite3.OperationalError as exc:
            raise sqlite_failure(exc, self.settings.data_dir / "queue.db") from exc

    def submit(self, job: Job) -> tuple[Job, bool]:
        """Store and enqueue `job`, or return the existing job with the same input key: (job, created)."""
        stored, created = self.store.add(job)
        if created:
            # The record beside the inputs: after `add`, so a rebuild never sees a submission that may yet be
            # deduplicated away; a loss of the store before it is written loses only this one submission.
            self.keep_record(stored)
            try:
                self.enqueue(stored.id)
            except StoreUnavailable as exc:  # the job is stored: `recover` finds it without a message, sends one
                log.warning("job %s: stored, but its queue message was not sent (a recovery pass will): %s",
                            stored.id, exc)
        return stored, created

    def cancel(self, job_id: str) -> Optional[Job]:
        """A queued job becomes cancelled at once; a running one gets cancel_requested, which its worker turns
        into `cancelled` within a heartbeat. Final jobs are returned unchanged."""
        def change(job: Job) -> Optional[Job]:
            if job.state == "queued":
                return job.ended("cancelled")
            if job.state == "running" and not job.cancel_requested:
                return job.model_copy(update={"cancel_requested": True})
            return None

        job = self.store.update(job_id, change)
        if job is not None and job.state == "cancelled":
            self.finished(job)
        return job

    def keep_record(self, job: Job) -> None:
        """The job's record as a file beside its inputs, and a succeeded one in its artifacts too, from which
        `rebuild_records` restores it if the store loses it (`bcf.jobs.recovery`)."""
        write_record(self.inputs_path(job.id), job)
        if job.state == "succeeded" and job.purged_at is None:
            write_record(self.artifacts_path(job.id), job)
        if self.storage.remote:
            try:  # a copy, as the files above: the store has the record
                self.storage.put_record(job.id, job)
            except ObjectStoreUnavailable as exc:
                log.warning("job %s: its record was not copied to object storage: %s", job.id, exc)

    def settle(self, job: Job) -> None:
        """A job whose outcome is stored: its record kept beside its files and, once it ended, its input images
        removed (no run needs them again; a resubmission uploads them anew). The record file stays, for a
        rebuild. Jobs still queued or running keep their inputs."""
        self.keep_record(job)
        if job.state in FINAL_STATES:
            self.remove_local_inputs(job.id)
            if self.storage.remote:
                try:
                    self.storage.remove_inputs(job.id)
                except ObjectStoreUnavailable as exc:  # left behind, harmless: a purge removes them
                    log.warning("job %s: its inputs were not removed from object storage: %s", job.id, exc)

    def remove_local_inputs(self, job_id: str) -> None:
        """The job's input images in the data folder, not its job.json."""
        folder = self.inputs_path(job_id)
        if folder.is_dir():
            for entry in folder.iterdir():
                if entry.name != RECORD_FILE:
                    shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() else entry.unlink(missing_ok=True)

    def finished(self, job: Job) -> None:
        """A job that just ended: `settle` it, and POST it to its callback_url (in the background)."""
        self.settle(job)
        send_callback(job, self.settings)

    def rebuild(self) -> RecoveryReport:
        """Restore the records the store lacks from the data folder (`bcf.jobs.recovery.rebuild_records`)."""
        report = rebuild_records(self)
        self.store.mark_rebuilt()
        moved = getattr(self.store, "moved_aside", [])  # unreadable SQLite files this process moved aside
        report.moved_aside = [str(path) for path in moved]
        moved.clear()
        level = logging.WARNING if report.changed() else logging.INFO
        for line in report.lines():
            log.log(level, "rebuild of the job records: %s", line)
        return report

    def rebuild_if_needed(self) -> Optional[RecoveryReport]:
        """`rebuild` if the store lost its records (or is new), else None."""
        return self.rebuild() if self.store.needs_rebuild() else None

    def pending_messages(self) -> int:
        return self.huey.pending_count()

    def recover(self) -> list[Job]:
        """Re-queue running jobs whose heartbeat is older than `stale_after_s` (their worker died), failing those
        that used all `max_attempts`; re-send the message of queued jobs that have none. Returns what changed."""
        now = utc_now()
        stale = datetime.timedelta(seconds=self.settings.stale_after_s)
        changed: list[Job] = []
        running, _ = self.store.list({"running"})
        for job in running:
            if (job.heartbeat_at or job.updated_at) < now - stale:
                # Its worker may have finished it but failed to record it: the result on disk counts.
                finished = finished_record(self, job.id)
                after = self.store.update(job.id, self._recover_change(now - stale, finished))
                if after is not None and after.state != "running":
                    if after.state == "queued":
                        self.enqueue(after.id)
                    elif after.state in FINAL_STATES:
                        self.finished(after)
                    changed.append(after)
        queued, _ = self.store.list({"queued"})
        if queued:
            with_message = {task.args[0] for task in self.huey.pending() if task.args}
            for job in queued:
                if job.id not in with_message and job.updated_at < now - stale:
                    # Touch it so the next pass does not re-send while a worker is about to claim it.
                    self.store.update(job.id, lambda j: j)
                    self.enqueue(job.id)
                    changed.append(job)
        return changed

    def _recover_change(self, threshold: datetime.datetime,
                        finished: Optional[Job] = None) -> Callable[[Job], Optional[Job]]:
        def change(job: Job) -> Optional[Job]:
            if job.state != "running" or (job.heartbeat_at or job.updated_at) >= threshold:
                return None  # it moved on, or a heartbeat arrived meanwhile
            if finished is not None:
                return finished
            lost = f"its worker {job.worker} stopped responding (attempt {job.attempts})"
            if job.cancel_requested:
                return job.ended("cancelled", error=lost)
            if job.attempts >= self.settings.max_attempts:
                return job.ended("failed", error=f"gave up after {job.attempts} attempts: {lost}")
            return job.requeued()
        return change

    def artifacts_path(self, job_id: str) -> Path:
        return self.settings.data_dir / "artifacts" / job_id

    def inputs_path(self, job_id: str) -> Path:
        return self.settings.data_dir / "inputs" / job_id

    def pack_artifacts(self, job: Job, folder: Path) -> Path:
        """Every result file of `job` (its `result.artifacts`) in one zip: a new file in `folder` that the caller
        removes once it is sent (result folders are not kept zipped: that would store every result twice)."""
        folder.mkdir(parents=True, exist_ok=True)
        handle = tempfile.NamedTemporaryFile(dir=folder, prefix="download-", suffix=".zip", delete=False)
        try:
            with handle, zipfile.ZipFile(handle, "w", zipfile.ZIP_DEFLATED) as archive:
                for name in job.result.artifacts if job.result else []:
                    with self.storage.open_artifact(job.id, name) as source, archive.open(name, "w") as target:
                        shutil.copyfileobj(source, target, 2**20)
        except BaseException:
            Path(handle.name).unlink(missing_ok=True)
            raise
        return Path(handle.name)

    def purge(self, job_id: str) -> Optional[Job]:
        """Remove a finished job's inputs and artifacts, keeping its record as a tombstone (`purged_at`), in the
        store and as the inputs folder's job.json. The record changes first, so no download starts on files about
        to go. Jobs not finished are unchanged."""
        def change(job: Job) -> Optional[Job]:
            return job.tombstone() if job.state in FINAL_STATES and job.purged_at is None else None

        job = self.store.update(job_id, change)
        if job is not None and job.purged_at is not None:
            shutil.rmtree(self.artifacts_path(job.id), ignore_errors=True)
            if self.storage.remote:
                try:  # the inputs go in `settle`, as for any ended job
                    self.storage.remove_artifacts(job.id)
                except ObjectStoreUnavailable as exc:  # the tombstone stands: nothing serves these objects
                    log.warning("job %s: purged, but its objects were not all removed: %s", job.id, exc)
            self.settle(job)  # the tombstone is what a rebuild restores
        return job

    def expire(self) -> list[Job]:
        """Purge the jobs that finished more than `retention_days` ago (none without retention)."""
        if self.settings.retention_days is None:
            return []
        threshold = utc_now() - datetime.timedelta(days=self.settings.retention_days)
        finished, _ = self.store.list(set(FINAL_STATES))
        expired = [job.id for job in finished
                   if job.purged_at is None and job.finished_at is not None and job.finished_at < threshold]
        return [job for job in map(self.purge, expired) if job is not None and job.purged_at is not None]

    def remove_partial_outputs(self, job_id: str) -> None:
        """Staging folders a killed worker left for this job's artifacts."""
        for leftover in staging_leftovers(self.artifacts_path(job_id)):
            shutil.rmtree(leftover, ignore_errors=True)
