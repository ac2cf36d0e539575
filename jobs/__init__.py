"""bcf.jobs: running many compressions: the job queue and its workers, the local batch runner, the benchmark.

`settings` (BCF_* environment), `records` (the stored job record), `store` (SQLite or Redis), `queue` (submit,
cancel, recover), `submission` (a checked job from uploaded files), `worker` (`bcf worker`), `batch` (a whole
asset tree, resumable, in local processes), `bench` (a materials folder at several sizes with baselines).
Knows no HTTP; calls `bcf.core`'s public API only. docs/SERVICE.md describes the queue.
"""
