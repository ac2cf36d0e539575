"""bcf.jobs: the job queue and its workers (Huey; SQLite embedded or Redis in farm mode).

`settings.Settings` (BCF_* environment), `records.Job` (the job object), `store` (job records), `queue.JobQueue`
(submit, cancel, recover), `worker.Worker` (`bcf worker`). docs/SERVICE.md describes the whole.
"""
