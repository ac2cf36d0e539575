"""`bcf admin`: maintenance of a service's data folder (thin layer over bcf.jobs).

Settings come from the environment or a .env file, as for `bcf serve` and `bcf worker`.
"""

from __future__ import annotations

import logging

from bcf.cli import say
from bcf.core import InputError


def recover() -> int:
    """Rebuild the job records from the data folder: after jobs.db was deleted or corrupted, or Redis lost its data.

    Each job's record is kept beside its files (inputs/ID/job.json, artifacts/ID/job.json). Records the store
    lacks are restored (unfinished jobs are queued again), unfinished jobs whose result is complete on disk
    become succeeded, and an unreadable jobs.db is moved aside (jobs.db.corrupt-TIME) for a new one. Folders
    without a record are listed, never removed. Running it again changes nothing more. Workers do the same at
    start and whenever the store lost its records; this command does it now, and says what it did.
    Settings come from the environment or a .env file: BCF_DATA_DIR, BCF_QUEUE_URL (see the README).
    """
    from bcf.service_cli import _settings
    from bcf.jobs.queue import JobQueue
    from bcf.jobs.store import StoreUnavailable

    settings = _settings()
    logging.getLogger("bcf.jobs").addHandler(logging.NullHandler())  # the report below says it all
    try:
        report = JobQueue(settings).rebuild()
    except StoreUnavailable as exc:
        raise InputError(f"the job store does not answer: {exc}") from None
    say(f"bcf admin recover: data in {settings.data_dir}, "
        f"{'farm mode, queue ' + str(settings.queue_url) if settings.farm_mode else 'embedded mode'}")
    for line in report.lines():
        say(f"  {line}")
    return 0


COMMANDS = (recover,)
