"""The job queue: job records in a `JobStore` plus Huey messages that tell workers which job to run.

Huey carries only job ids; the record is the truth. A worker claims a job by moving it from queued to
running in the store, so a duplicate message (a re-queue racing a slow worker) is a no-op. Jobs are never
lost: the store persists them (SQLite file or Redis), Huey persists its messages, and `recover` re-queues
jobs whose worker stopped sending heartbeats and queued jobs whose message is missing.
"""

from __future__ import annotations

import datetime
import shutil
from pathlib import Path
from typing import Callable, Optional

from huey import Huey, RedisHuey, SqliteHuey

from bcf.core import staging_leftovers
from bcf.jobs.records import Job, utc_now
from bcf.jobs.settings import Settings
from bcf.jobs.store import JobStore, open_store

__all__ = ["JobQueue", "RUN_JOB_TASK", "make_huey"]

RUN_JOB_TASK = "bcf.run_job"
JobRunner = Callable[[str], None]


def make_huey(settings: Settings) -> Huey:
    """RedisHuey on BCF_QUEUE_URL, else SqliteHuey in the data directory. No result store: results are files."""
    if settings.queue_url:
        return RedisHuey("bcf", url=settings.queue_url, results=False)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    return SqliteHuey("bcf", filename=str(settings.data_dir / "queue.db"), results=False)


class JobQueue:
    """Submit, cancel and recover jobs. `runner` is the function a worker runs for a job id (None in the API)."""

    def __init__(self, settings: Settings, runner: Optional[JobRunner] = None,
                 store: Optional[JobStore] = None):
        self.settings = settings
        self.store = store or open_store(settings)
        self.huey = make_huey(settings)

        def run_job(job_id: str) -> None:
            if runner is None:
                raise RuntimeError("this process only submits jobs; run them with 'bcf worker'")
            runner(job_id)

        self._task = self.huey.task(name=RUN_JOB_TASK)(run_job)

    def enqueue(self, job_id: str) -> None:
        self._task(job_id)

    def submit(self, job: Job) -> tuple[Job, bool]:
        """Store and enqueue `job`, or return the existing job with the same input key: (job, created)."""
        stored, created = self.store.add(job)
        if created:
            self.enqueue(stored.id)  # if this fails, `recover` finds the queued job without a message
        return stored, created

    def cancel(self, job_id: str) -> Optional[Job]:
        """A queued job becomes cancelled at once; a running one gets cancel_requested, which its worker turns
        into `cancelled` within a heartbeat. Final jobs are returned unchanged."""
        def change(job: Job) -> Optional[Job]:
            if job.state == "queued":
                return job.model_copy(update={"state": "cancelled", "finished_at": utc_now(),
                                              "progress": job.progress.model_copy(update={"stage": "cancelled"})})
            if job.state == "running" and not job.cancel_requested:
                return job.model_copy(update={"cancel_requested": True})
            return None

        return self.store.update(job_id, change)

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
                after = self.store.update(job.id, self._recover_change(now - stale))
                if after is not None and after.state != "running":
                    if after.state == "queued":
                        self.enqueue(after.id)
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

    def _recover_change(self, threshold: datetime.datetime) -> Callable[[Job], Optional[Job]]:
        def change(job: Job) -> Optional[Job]:
            if job.state != "running" or (job.heartbeat_at or job.updated_at) >= threshold:
                return None  # it moved on, or a heartbeat arrived meanwhile
            lost = f"its worker {job.worker} stopped responding (attempt {job.attempts})"
            if job.cancel_requested:
                return job.model_copy(update={"state": "cancelled", "finished_at": utc_now(), "error": lost})
            if job.attempts >= self.settings.max_attempts:
                return job.model_copy(update={
                    "state": "failed", "finished_at": utc_now(),
                    "error": f"gave up after {job.attempts} attempts: {lost}",
                    "progress": job.progress.model_copy(update={"stage": "failed"})})
            return job.model_copy(update={"state": "queued", "worker": None, "error": None,
                                          "progress": job.progress.model_copy(update={"stage": "queued"})})
        return change

    def artifacts_path(self, job_id: str) -> Path:
        return self.settings.artifacts_dir / job_id

    def inputs_path(self, job_id: str) -> Path:
        return self.settings.inputs_dir / job_id

    def remove_partial_outputs(self, job_id: str) -> None:
        """Staging folders a killed worker left for this job's artifacts."""
        for leftover in staging_leftovers(self.artifacts_path(job_id)):
            shutil.rmtree(leftover, ignore_errors=True)
