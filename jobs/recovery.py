"""Job records kept beside their files, and the rebuild of lost job records from them.

The data folder describes itself: `inputs/<id>/job.json` holds a job's record from the moment it is stored (and
again when it ends), `artifacts/<id>/job.json` its succeeded record, written once the result is complete and
before the store is told. If the store loses its records (jobs.db deleted or corrupt, Redis flushed), or a
worker could not record a result, `rebuild_records` puts them back: run by every worker's recovery pass when the
store says it needs it, by a SQLite store that just recreated its file, and by `bcf admin recover`.

The artifacts' job.json is bookkeeping (tenant, input key, worker): it is not one of `result.artifacts`, so
downloads leave it out.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Optional

from pydantic import BaseModel

from bcf.jobs.records import RECORD_FILE, Job, read_record
from bcf.jobs.storage import ObjectStoreUnavailable

if TYPE_CHECKING:
    from bcf.jobs.queue import JobQueue

__all__ = ["RecoveryReport", "finished_record", "rebuild_records"]

log = logging.getLogger("bcf.jobs")


class RecoveryReport(BaseModel):
    """What a rebuild did; each entry names a job id (or a folder, relative to the data folder)."""

    restored: list[str] = []  # "<id> <state>": records put back into the store
    requeued: list[str] = []  # restored unfinished jobs, sent to the workers again
    adopted: list[str] = []  # unfinished jobs in the store whose complete result was on disk: now succeeded
    kept: list[str] = []  # stored jobs whose folders had no job.json (stored before records were kept): written
    orphans: list[str] = []  # folders without a readable record, left as they are
    moved_aside: list[str] = []  # unreadable database files, kept under a new name

    def changed(self) -> bool:
        return bool(self.restored or self.adopted or self.moved_aside)

    def lines(self) -> list[str]:
        """The report for people: one line per kind of change."""
        kinds = (("moved aside (unreadable)", self.moved_aside), ("restored", self.restored),
                 ("re-queued", self.requeued), ("succeeded (result found on disk)", self.adopted),
                 ("records written beside their files", self.kept),
                 ("orphan folders (no job record; kept)", self.orphans))
        return [f"{what}: {len(items)}" + (f": {', '.join(items)}" if items else "") for what, items in kinds]


def finished_record(queue: "JobQueue", job_id: str) -> Optional[Job]:
    """The succeeded record of the job's complete result in its storage (`bcf.jobs.storage`): in the data folder,
    the artifacts folder's job.json if the folder holds every file it names; in object storage, the commit
    marker's. None also when the object storage does not answer (the next pass asks again)."""
    try:
        return queue.storage.finished_record(job_id)
    except ObjectStoreUnavailable as exc:
        log.warning("job %s: its result could not be looked for: %s", job_id, exc)
        return None


def _from_inputs(job: Job) -> Job:
    """A record kept with the inputs, as it is restored: unfinished jobs queued again, a success whose result
    is gone failed (resubmitting makes a new job); a purged job's tombstone as it is."""
    if job.state in ("queued", "running"):
        return job.requeued()
    if job.state == "succeeded" and job.purged_at is None:
        return job.ended("failed", error="its result files were lost (found by recovery); submit it again")
    return job


def _recover_one(queue: "JobQueue", job_id: str, report: RecoveryReport) -> None:
    finished = finished_record(queue, job_id)
    stored = queue.store.get(job_id)
    if stored is not None:
        if finished is not None and stored.state in ("queued", "running"):
            # A worker finished it but could not record it (and died, or gave up at shutdown).
            after = queue.store.update(job_id, lambda j: finished if j.state in ("queued", "running") else None)
            if after is not None and after.state == "succeeded":
                report.adopted.append(job_id)
                stored = after
        folders = [queue.inputs_path(job_id)] + ([queue.artifacts_path(job_id)] if stored.state == "succeeded" else [])
        if any(folder.is_dir() and not (folder / RECORD_FILE).exists() for folder in folders):
            queue.keep_record(stored)  # a job stored before records were kept beside its files
            report.kept.append(job_id)
        return
    submitted = read_record(queue.inputs_path(job_id)) or queue.storage.record(job_id)
    record = finished or (None if submitted is None else _from_inputs(submitted))
    if record is None:
        kinds = [kind for kind, path in (("inputs", queue.inputs_path(job_id)),
                                         ("artifacts", queue.artifacts_path(job_id))) if path.is_dir()]
        report.orphans.extend(f"{kind}/{job_id}" for kind in kinds)
        return
    if queue.store.restore(record):
        report.restored.append(f"{job_id} {record.state}")
        if record.state == "queued":
            queue.enqueue(job_id)
            report.requeued.append(job_id)


def _job_folders(root: Path) -> set[str]:
    """Names of the job folders under `root`; hidden ones are staging folders of results being written."""
    if not root.is_dir():
        return set()
    return {p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")}


def rebuild_records(queue: "JobQueue") -> RecoveryReport:
    """Restore the record of every job folder the store has no record of, from its job.json (the artifacts'
    succeeded record first, else the inputs' one), and mark unfinished jobs succeeded whose result is complete
    on disk. Folders without a record are reported, never removed. Running it again changes nothing more."""
    report = RecoveryReport()
    data = queue.settings.data_dir
    stored = queue.storage.job_ids()  # object storage: the jobs it holds (the data folder is scratch)
    for job_id in sorted(_job_folders(data / "inputs") | _job_folders(data / "artifacts") | stored):
        _recover_one(queue, job_id, report)
    return report
