"""`bcf worker`: a Huey consumer that runs compression jobs with `bcf.core.pipeline.compress_material`.

A job runs in a consumer thread; a monitor thread beside it writes progress and a heartbeat to the job
record every `heartbeat_s` and notices cancel requests. A cancel request or a shutdown stops training at the
next iteration (`should_stop`); a shutdown puts the job back in the queue for another worker. An outcome the
store cannot take is kept (a result describes itself on disk) and recorded again until the store takes it.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import threading
import time
import traceback
import uuid
from pathlib import Path
from typing import Any, Callable, Optional

from tenacity import RetryCallState, Retrying, retry_if_exception_type, wait_exponential

from bcf.core import TrainingProgress, TrainingStopped, compress_material, failure_text, resolve_options
from bcf.jobs.queue import JobQueue
from bcf.jobs.records import FINAL_STATES, Job, JobProgress, JobResult, utc_now
from bcf.jobs.settings import Settings
from bcf.jobs.storage import ObjectStoreUnavailable
from bcf.jobs.store import JobStore, StoreUnavailable
from bcf.jobs.submission import load_job_material

__all__ = ["Worker"]

log = logging.getLogger("bcf.worker")
SHUTDOWN_GRACE_S = 10.0
RECORD_RETRY_MAX_S = 5.0  # longest pause between attempts to record an outcome the store did not take


class _Monitor:
    """Heartbeat, progress and cancel requests of one running job, on its own thread."""

    def __init__(self, store: JobStore, job: Job, worker_id: str, interval_s: float, phase2_iterations: int):
        self.store, self.job_id, self.worker_id = store, job.id, worker_id
        self.interval_s, self.phase2_iterations = interval_s, phase2_iterations
        self.progress = JobProgress(stage="loading")
        self.cancel = threading.Event()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"monitor-{job.id}", daemon=True)

    def __enter__(self) -> "_Monitor":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._thread.join()

    def on_progress(self, p: TrainingProgress) -> None:
        left = p.total - p.iteration + (self.phase2_iterations if p.phase == 1 else 0)
        self.progress = JobProgress(stage="training", phase=p.phase, iteration=p.iteration, total=p.total,
                                    psnr=round(p.psnr, 3), eta_s=round(left / max(p.iterations_per_s, 1e-9), 1))

    def on_note(self, text: str) -> None:
        self.progress = self.progress.model_copy(update={"stage": text, "eta_s": None})

    def _run(self) -> None:
        while not self._done.wait(self.interval_s):
            self.beat()

    def beat(self) -> None:
        progress = self.progress

        def change(job: Job) -> Optional[Job]:
            if job.state != "running" or job.worker != self.worker_id:
                return None
            return job.model_copy(update={"heartbeat_at": utc_now(), "progress": progress})

        try:
            job = self.store.update(self.job_id, change)
        except StoreUnavailable as exc:  # keep training; the next beat may get through
            log.warning("job %s: heartbeat not stored: %s", self.job_id, exc)
            return
        if job is None or job.cancel_requested or job.worker != self.worker_id or job.state != "running":
            self.cancel.set()  # cancelled, or the job was given to another worker: stop working on it


class Worker:
    """Runs jobs from the queue on one torch device."""

    def __init__(self, settings: Settings, device: str = "cpu"):
        self.settings = settings
        self.device = device
        self.id = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
        self.queue = JobQueue(settings, runner=self.run_job)
        self.shutdown = threading.Event()
        self._consumer_stop: Optional[Any] = None  # huey's stop flag while `serve` runs
        self._held: set[str] = set()
        self._lock = threading.Lock()

    def stopping(self) -> bool:
        """A shutdown was asked for: by a signal to the consumer, or by `serve` ending."""
        return self.shutdown.is_set() or (self._consumer_stop is not None and self._consumer_stop.is_set())

    def _claim(self, job: Job) -> Optional[Job]:
        if job.state != "queued":
            return None
        return job.model_copy(update={"state": "running", "attempts": job.attempts + 1, "worker": self.id,
                                      "options": job.options.model_copy(update={"device": self.device}),
                                      "started_at": utc_now(), "heartbeat_at": utc_now(), "error": None,
                                      "progress": JobProgress(stage="loading")})

    def _update_held(self, job_id: str, change: Callable[[Job], Job]) -> Optional[Job]:
        """Change a job only while this worker holds it: if it looked dead, the job was re-queued meanwhile
        and another run owns it now."""
        def held(job: Job) -> Optional[Job]:
            return change(job) if job.state == "running" and job.worker == self.id else None
        return self.queue.store.update(job_id, held)

    def _record(self, job_id: str, change: Callable[[Job], Job], what: str) -> Optional[Job]:
        """`_update_held`, again and again while the store fails (Redis down, a locked or lost database): an
        outcome is not dropped. Gives up only when the worker stops; a result's job.json in its artifacts folder
        then lets the next recovery pass record it (`bcf.jobs.recovery`)."""
        def note_retry(state: RetryCallState) -> None:
            log.warning("job %s: %s not recorded yet (%s); trying again in %.1f s", job_id, what,
                        state.outcome.exception() if state.outcome else "", state.upcoming_sleep)

        # Whatever the store raises is the store's trouble, not the job's; the pause ends early at shutdown.
        retrying = Retrying(retry=retry_if_exception_type(Exception), stop=lambda state: self.stopping(),
                            wait=wait_exponential(multiplier=0.5, max=RECORD_RETRY_MAX_S), sleep=self.shutdown.wait,
                            before_sleep=note_retry, reraise=True)
        try:
            return retrying(self._update_held, job_id, change)
        except Exception as exc:
            log.error("job %s: %s not recorded (%s); the worker is stopping: recovery records it from the data "
                      "folder", job_id, what, exc)
            return None

    def _end(self, job_id: str, change: Callable[[Job], Job], what: str) -> Optional[Job]:
        """Record the outcome (`_record`), then settle the job: its record beside its files, its input images
        removed, its callback sent (`JobQueue.finished`)."""
        job = self._record(job_id, change, what)
        if job is not None and job.state in FINAL_STATES:
            self.queue.finished(job)
        return job

    def release(self, job_id: str) -> None:
        """Give a job this worker holds back to the queue (shutdown, an object store failure): another worker
        restarts it."""
        job = self._update_held(job_id, Job.requeued)
        if job is not None and job.state == "queued":
            self.queue.enqueue(job_id)
            log.info("job %s: back in the queue", job_id)

    def run_job(self, job_id: str) -> None:
        """The Huey task: claim the job, compress, record the outcome. Never raises for a job's own failure."""
        if self.stopping():
            return  # the job stays queued and its message is re-sent by `recover`
        job = self.queue.store.update(job_id, self._claim)
        if job is None or job.state != "running" or job.worker != self.id:
            return  # cancelled, or already run: a duplicate message
        with self._lock:
            self._held.add(job_id)
        try:
            self._run_claimed(job)
        finally:
            with self._lock:
                self._held.discard(job_id)

    def _run_claimed(self, job: Job) -> None:
        started = time.perf_counter()
        resolved = resolve_options(job.options.compress_options())  # the claim set the device: ours
        log.info("job %s: %s, attempt %d, preset %s on %s", job.id, job.name, job.attempts, resolved.preset,
                 self.device)
        self.queue.remove_partial_outputs(job.id)
        output = self.queue.artifacts_path(job.id)
        deadline = time.monotonic() + self.settings.job_time_limit_s
        with _Monitor(self.queue.store, job, self.id, self.settings.heartbeat_s,
                      resolved.phase2_iterations) as monitor:
            def should_stop() -> bool:
                return monitor.cancel.is_set() or self.stopping() or time.monotonic() > deadline
            try:
                self.queue.storage.fetch_inputs(job.id, self.queue.inputs_path(job.id))
                texture_set = load_job_material(job, self.queue.inputs_path(job.id), self.settings)
                self._record_notes(job.id, texture_set.notes)
                report = compress_material(
                    texture_set, resolved, output, progress=monitor.on_progress,
                    should_stop=should_stop, overwrite=True,
                    baselines=job.options.baselines, note=monitor.on_note)
                artifacts = sorted(str(p.relative_to(output)) for p in output.rglob("*") if p.is_file())
                result = JobResult(psnr=report.aggregate.psnr.all, ssim=report.aggregate.ssim.all,
                                   artifacts=artifacts, size_bytes=report.size.total_bytes,
                                   bits_per_texel=report.size.bits_per_texel)
                # The result describes itself before the store hears of it: if recording fails for good, or the
                # store loses the record, recovery finds it complete on disk (or committed in object storage).
                record = job.ended("succeeded", monitor.progress, result=result)
                self.queue.keep_record(record)
                if self.queue.storage.remote:  # under the monitor: a slow upload keeps the heartbeat going
                    monitor.on_note("uploading")
                    log.info("job %s: uploading %d result files to %s", job.id, len(artifacts),
                             self.settings.storage_url)
                    self.queue.storage.put_artifacts(job.id, output, record)
            except TrainingStopped:
                if time.monotonic() > deadline and not monitor.cancel.is_set() and not self.stopping():
                    limit = (f"stopped after {time.perf_counter() - started:.0f} s: longer than the wall-clock limit "
                             f"of {self.settings.job_time_limit_s:g} s per job (BCF_JOB_TIME_LIMIT_S)")
                    self._end(job.id, lambda held: held.ended("failed", monitor.progress, error=limit), "its failure")
                    log.error("job %s: %s", job.id, limit)
                    return
                if self.stopping() and not monitor.cancel.is_set():
                    self.release(job.id)
                    return
                self._end(job.id, lambda held: held.ended("cancelled", monitor.progress), "its cancellation")
                log.info("job %s: cancelled", job.id)
                return
            except ObjectStoreUnavailable as exc:  # the store's trouble: another attempt may get through
                self._storage_failed(job, exc, monitor.progress)
                return
            except Exception as exc:  # any failure of one job is that job's, not the worker's
                message = failure_text(exc, file=lambda path: Path(path).name)  # never server paths
                self._end(job.id, lambda held: held.ended("failed", monitor.progress, error=message),
                          "its failure")
                log.error("job %s: failed: %s\n%s", job.id, message, traceback.format_exc())
                return
        done = self._end(job.id, lambda held: held.ended("succeeded", monitor.progress, result=result),
                         "its result")
        if self.queue.storage.remote:  # committed in object storage: the local copy was scratch
            shutil.rmtree(output, ignore_errors=True)
        if done is not None and done.state == "succeeded":
            log.info("job %s: succeeded in %.1f s, %.2f dB", job.id, time.perf_counter() - started,
                     report.aggregate.psnr.all)

    def _storage_failed(self, job: Job, exc: ObjectStoreUnavailable, progress: JobProgress) -> None:
        """Object storage failed the attempt: back in the queue while attempts are left, else failed saying why."""
        if self.queue.storage.remote:  # scratch copies: the next attempt, on any worker, fetches the inputs again
            shutil.rmtree(self.queue.artifacts_path(job.id), ignore_errors=True)
            self.queue.remove_local_inputs(job.id)
        if job.attempts < self.settings.max_attempts:
            log.warning("job %s: attempt %d of %d failed, object storage unavailable (%s); back in the queue",
                        job.id, job.attempts, self.settings.max_attempts, exc)
            self.release(job.id)
            return
        message = f"gave up after {job.attempts} attempts (BCF_MAX_ATTEMPTS): {exc}"
        self._end(job.id, lambda held: held.ended("failed", progress, error=message), "its failure")
        log.error("job %s: %s", job.id, message)

    def _record_notes(self, job_id: str, notes: tuple[str, ...]) -> None:
        """What decoding the pixels noticed (a flipped-looking normal map, clipped values) joins the notes the
        API found in the headers. A store that does not answer loses the notes, not the job: the report has them."""
        def add(job: Job) -> Job:
            return job.model_copy(update={"notes": [*job.notes, *(n for n in notes if n not in job.notes)]})
        try:
            self._update_held(job_id, add)
        except StoreUnavailable as exc:
            log.warning("job %s: notes not stored: %s", job_id, exc)

    def _recover_forever(self) -> None:
        interval = max(1.0, self.settings.stale_after_s / 3)
        while not self.shutdown.wait(interval):
            self._recover()

    def _recover(self) -> None:
        try:
            self.queue.rebuild_if_needed()  # the store lost its records (or is new): back from the data folder
        except StoreUnavailable as exc:
            log.warning("rebuild of the job records skipped: %s", exc)
        except OSError as exc:  # an unreadable data folder must not end the recovery thread; tried again next pass
            log.error("rebuild of the job records failed: %s", exc)
        try:
            for job in self.queue.recover():
                log.info("job %s: recovered -> %s", job.id, job.state)
            for job in self.queue.expire():
                log.info("job %s: files removed, finished more than BCF_RETENTION_DAYS ago", job.id)
        except StoreUnavailable as exc:
            log.warning("recovery pass skipped: %s", exc)

    def serve(self, concurrency: int = 1) -> None:
        """Consume jobs until SIGTERM or SIGINT; jobs still running then go back to the queue."""
        # SIGTERM (docker stop, bcf serve's shutdown) is graceful: running jobs stop at the next iteration and
        # are released; SIGINT stops at once and releases from here.
        consumer = self.queue.huey.create_consumer(workers=concurrency, worker_type="thread", periodic=False,
                                                   initial_delay=0.1, backoff=1.15, max_delay=1.0,
                                                   graceful_signal="TERM")
        self._consumer_stop = consumer.stop_flag  # set by huey on a signal: our jobs stop too
        log.info("worker %s: %s mode, device %s, %d at a time, data in %s%s", self.id,
                 "farm (Redis)" if self.settings.farm_mode else "embedded (SQLite)", self.device, concurrency,
                 self.settings.data_dir, f", inputs and results in {self.settings.storage_url}"
                 if self.settings.storage_url else "")
        self._recover()
        recovery = threading.Thread(target=self._recover_forever, name="recovery", daemon=True)
        recovery.start()
        try:
            consumer.run()
        finally:
            self.shutdown.set()
            # Jobs in training stop at their next iteration and release themselves; give them that moment
            # (exiting under a thread that is inside torch aborts the process). A job still evaluating after
            # the grace period is released here and rerun elsewhere.
            deadline = time.monotonic() + SHUTDOWN_GRACE_S
            while self._held and time.monotonic() < deadline:
                time.sleep(0.05)
            with self._lock:
                held = list(self._held)
            for job_id in held:
                self.release(job_id)
            log.info("worker %s: stopped", self.id)
            if held:
                os._exit(1)  # threads still inside torch: skip interpreter teardown
