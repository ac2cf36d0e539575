"""GET /metrics: Prometheus text exposition of the job store and queue."""

from __future__ import annotations

from typing import Optional

from bcf.jobs.queue import JobQueue
from bcf.jobs.records import FINAL_STATES, JOB_STATES
from bcf.jobs.store import free_disk_bytes
from bcf.jobs.supervisor import WorkerStatus

__all__ = ["DURATION_BUCKETS_S", "prometheus_text"]

# Job run times (started -> finished) span seconds (fast preset, small materials) to hours (paper preset, 2K).
DURATION_BUCKETS_S = (1, 5, 15, 60, 300, 900, 3600, 4 * 3600, 12 * 3600)


def prometheus_text(queue: JobQueue, workers: Optional[WorkerStatus] = None, refused_for_disk: int = 0) -> str:
    """The metrics; `refused_for_disk`: uploads this server process refused with 507 since it started."""
    jobs, _ = queue.store.list()  # the finished ones are most of them, and their durations are needed anyway
    lines = ["# HELP bcf_jobs Jobs in the store by state.", "# TYPE bcf_jobs gauge"]
    lines += [f'bcf_jobs{{state="{state}"}} {sum(job.state == state for job in jobs)}' for state in JOB_STATES]
    lines += ["# HELP bcf_jobs_purged Finished jobs whose files were removed (purged or expired): tombstones.",
              "# TYPE bcf_jobs_purged gauge", f"bcf_jobs_purged {sum(job.purged_at is not None for job in jobs)}"]
    settings = queue.settings
    lines += ["# HELP bcf_disk_free_bytes Free space on the data directory's disk.",
              "# TYPE bcf_disk_free_bytes gauge", f"bcf_disk_free_bytes {free_disk_bytes(settings.data_dir)}",
              "# HELP bcf_disk_min_free_bytes The floor below which uploads are refused (BCF_MIN_FREE_DISK_MB).",
              "# TYPE bcf_disk_min_free_bytes gauge", f"bcf_disk_min_free_bytes {settings.min_free_disk_bytes}",
              "# HELP bcf_uploads_refused_total Uploads this server refused (507) for lack of disk space.",
              "# TYPE bcf_uploads_refused_total counter", f'bcf_uploads_refused_total{{reason="disk"}} {refused_for_disk}']
    lines += ["# HELP bcf_queue_depth Messages waiting in the queue for a worker.", "# TYPE bcf_queue_depth gauge",
              f"bcf_queue_depth {queue.pending_messages()}"]
    lines += ["# HELP bcf_job_duration_seconds Run time of finished jobs (start of the last attempt to end).",
              "# TYPE bcf_job_duration_seconds histogram"]
    for state in sorted(FINAL_STATES):
        durations = [d for job in jobs if job.state == state and (d := job.duration_s) is not None]
        for bound in DURATION_BUCKETS_S:
            lines.append(f'bcf_job_duration_seconds_bucket{{state="{state}",le="{bound}"}} '
                         f"{sum(d <= bound for d in durations)}")
        lines.append(f'bcf_job_duration_seconds_bucket{{state="{state}",le="+Inf"}} {len(durations)}')
        lines.append(f'bcf_job_duration_seconds_sum{{state="{state}"}} {sum(durations):.3f}')
        lines.append(f'bcf_job_duration_seconds_count{{state="{state}"}} {len(durations)}')
    if workers is not None:  # the workers `bcf serve` supervises
        lines += ["# HELP bcf_workers Worker processes this server keeps, and of them running now.",
                  "# TYPE bcf_workers gauge", f'bcf_workers{{state="wanted"}} {workers.wanted}',
                  f'bcf_workers{{state="live"}} {workers.live}',
                  "# HELP bcf_worker_restarts_total Workers started to replace dead ones.",
                  "# TYPE bcf_worker_restarts_total counter", f"bcf_worker_restarts_total {workers.restarts}"]
    return "\n".join(lines) + "\n"
