"""Nothing is lost with the job store (issue 16, case 4): every job's record is also kept beside its files
(inputs/<id>/job.json, artifacts/<id>/job.json), a deleted or corrupt jobs.db heals itself and is rebuilt from
them, as is a flushed Redis; `bcf admin recover` does it on demand; a worker that cannot record a result keeps
it and tries again. Real stores, real `bcf serve` / `bcf worker` / `redis-server` processes."""

from __future__ import annotations

import datetime
import io
import json
import subprocess
import uuid
import zipfile
from pathlib import Path
from typing import Any

import pytest
import redis

from bcf.core.options import JobOptions
from bcf.jobs.queue import JobQueue
from bcf.jobs.records import InputFile, Job, JobResult, utc_now
from bcf.jobs.records import read_record, write_record
from bcf.jobs.recovery import RecoveryReport
from bcf.jobs.settings import Settings
from bcf.jobs.store import JobStore, RedisJobStore, SqliteJobStore
from bcf_command import BCF
from service_harness import TINY_OPTIONS, BcfEnvironment, redis_server, tiny_material, wait_until

# A few seconds of training on 64x64: long enough to be caught running.
SECONDS_OPTIONS = {"preset": "fast", "phase1_iterations": 600, "phase2_iterations": 600, "batch_size": 1024}


def submit(server: Any, variant: int, options: dict) -> dict[str, Any]:
    response = server.client.post("/v1/jobs", files=tiny_material(variant), data={"options": json.dumps(options)})
    assert response.status_code == 202, response.text
    return response.json()


def remove_database(data_dir: Path) -> None:
    for name in ("jobs.db", "jobs.db-wal", "jobs.db-shm"):
        (data_dir / name).unlink(missing_ok=True)


def a_job(tenant: str = "default") -> Job:
    inputs = [InputFile(role="albedo", name="Color.png", stored_as="albedo/Color.png", sha256="0" * 64, bytes=1)]
    return Job(id=uuid.uuid4().hex[:16], name="test", options=JobOptions(), inputs=inputs,
               input_key=uuid.uuid4().hex, tenant=tenant)


# ----------------------------------------------------------------------------------------------- the stores


def test_a_deleted_sqlite_database_is_recreated_and_the_rebuild_hook_runs(tmp_path: Path) -> None:
    rebuilds: list[int] = []
    store = SqliteJobStore(tmp_path / "jobs.db", on_recreated=lambda: rebuilds.append(1))
    job, _ = store.add(a_job())
    store.mark_rebuilt()
    assert not store.needs_rebuild()
    remove_database(tmp_path)
    # The next operation finds a new, empty file ("no such table"): it recreates the schema, calls the hook once,
    # and answers, instead of failing from now on.
    assert store.list() == ([], 0)
    assert rebuilds == [1]
    assert store.needs_rebuild()  # the new file was never rebuilt from the data folder
    assert store.restore(job) and store.get(job.id) == job and not store.restore(job)
    assert rebuilds == [1] and store.moved_aside == []


def test_a_corrupt_sqlite_database_is_moved_aside_never_deleted(tmp_path: Path) -> None:
    store = SqliteJobStore(tmp_path / "jobs.db")
    store.add(a_job())
    garbage = b"not a database " * 400
    remove_database(tmp_path)
    (tmp_path / "jobs.db").write_bytes(garbage)
    assert store.get("nothing") is None  # not "file is not a database" for good
    [aside] = store.moved_aside
    assert aside.name.startswith("jobs.db.corrupt-") and aside.read_bytes() == garbage
    assert store.needs_rebuild() and store.list() == ([], 0)
    # A store opened on a corrupt file (a process starting after the damage) does the same.
    (tmp_path / "jobs.db").write_bytes(garbage)
    again = SqliteJobStore(tmp_path / "jobs.db")
    assert len(again.moved_aside) == 1 and again.moved_aside[0].read_bytes() == garbage
    assert again.list() == ([], 0)


@pytest.mark.parametrize("kind", ["sqlite", "redis"])
def test_restore_keeps_existing_records_and_the_rebuild_mark(kind: str, tmp_path: Path, redis_url: str) -> None:
    prefix = f"t{uuid.uuid4().hex}"
    store: JobStore = (SqliteJobStore(tmp_path / "jobs.db") if kind == "sqlite"
                       else RedisJobStore(redis_url, prefix=prefix))
    assert store.needs_rebuild()  # a new store: its records (none) come from the data folder
    store.mark_rebuilt()
    assert not store.needs_rebuild()
    job = a_job(tenant="alice").ended("succeeded")
    assert store.restore(job)
    assert not store.restore(job.model_copy(update={"state": "failed"}))  # the stored record wins
    assert store.get(job.id) == job
    assert store.list({"succeeded"}, tenant="alice") == ([job], 1)
    assert store.add(job.model_copy(update={"id": "other"})) == (job, False)  # it holds its input key again
    if kind == "redis":
        redis.Redis.from_url(redis_url).flushdb()
        assert store.needs_rebuild()


def test_bcf_admin_recover_says_so_when_the_store_does_not_answer(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, queue_url="redis://127.0.0.1:1/0")  # nothing listens on port 1
    result = subprocess.run([*BCF, "admin", "recover"], capture_output=True, text=True, env=environment.env,
                            timeout=120)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.startswith("bcf: error: the job store does not answer: job store (Redis):"), result.stderr
    assert len(result.stderr.splitlines()) == 1


# --------------------------------------------------------------------------------------- embedded (SQLite)


def test_a_finished_job_survives_deleting_jobs_db_while_the_service_runs(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, heartbeat_s=0.5)
    server = environment.serve(workers=1)
    try:
        job = submit(server, 20, TINY_OPTIONS)
        done = server.wait_finished(job["id"])
        assert done["state"] == "succeeded", done["error"]
        kept = json.loads((environment.data_dir / "artifacts" / job["id"] / "job.json").read_text())
        assert kept["state"] == "succeeded" and kept["result"] == done["result"]

        remove_database(environment.data_dir)
        listed = server.client.get("/v1/jobs")
        assert listed.status_code == 200, listed.text  # not 503, now or ever
        [back] = listed.json()["jobs"]
        assert back["id"] == job["id"] and back["state"] == "succeeded" and back["result"] == done["result"]
        archive = server.client.get(f"/v1/jobs/{job['id']}/artifacts")
        assert archive.status_code == 200, archive.text
        with zipfile.ZipFile(io.BytesIO(archive.content)) as z:
            assert sorted(z.namelist()) == sorted(done["result"]["artifacts"])  # the record is not a result file
        again = server.client.post("/v1/jobs", files=tiny_material(20), data={"options": json.dumps(TINY_OPTIONS)})
        assert again.status_code == 200 and again.json()["id"] == job["id"]  # it holds its inputs' key again
        assert "job records rebuilt" not in server.log.read_text()  # the API healed itself, no restart
    finally:
        server.stop()


def test_running_and_queued_jobs_whose_records_are_lost_are_rebuilt_and_complete(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, heartbeat_s=0.5)
    server = environment.serve(workers=0)
    worker = None
    try:
        running = submit(server, 21, SECONDS_OPTIONS)
        queued = submit(server, 22, TINY_OPTIONS)
        worker = environment.worker()  # one job at a time: the second waits in the queue
        server.wait_for_job(running["id"], lambda j: j["state"] == "running" and j["progress"]["iteration"] > 0,
                            60, "to be training", logs=(worker.log,))
        remove_database(environment.data_dir)
        # Rebuilt from inputs/<id>/job.json: both queued again, their messages sent again.
        listed = server.client.get("/v1/jobs").json()
        assert {j["id"] for j in listed["jobs"]} == {running["id"], queued["id"]}
        for job in (running, queued):
            done = server.wait_finished(job["id"], timeout=120, logs=(worker.log,))
            assert done["state"] == "succeeded", done["error"]
    finally:
        if worker is not None:
            worker.stop()
        server.stop()


def test_bcf_admin_recover_rebuilds_the_records_of_a_corrupt_jobs_db(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, api_tokens="alice:a-token")
    server = environment.serve(workers=0)
    try:
        cancelled = submit(server, 23, TINY_OPTIONS)
        assert server.client.delete(f"/v1/jobs/{cancelled['id']}").json()["state"] == "cancelled"
        succeeded = submit(server, 24, TINY_OPTIONS)
        worker = environment.worker()
        try:
            assert server.wait_finished(succeeded["id"], logs=(worker.log,))["state"] == "succeeded"
        finally:
            worker.stop()
        before = {job_id: server.stored(job_id) for job_id in (cancelled["id"], succeeded["id"])}
    finally:
        server.stop()
    (environment.data_dir / "inputs" / "orphan").mkdir()  # a folder without a record: reported, kept
    garbage = b"\x00garbage" * 1000
    remove_database(environment.data_dir)
    (environment.data_dir / "jobs.db").write_bytes(garbage)

    def recover() -> subprocess.CompletedProcess[str]:
        return subprocess.run([*BCF, "admin", "recover"], capture_output=True, text=True, env=environment.env,
                              timeout=120)

    first = recover()
    assert first.returncode == 0, first.stderr
    assert "moved aside (unreadable): 1" in first.stdout and "restored: 2" in first.stdout, first.stdout
    assert f"{succeeded['id']} succeeded" in first.stdout and f"{cancelled['id']} cancelled" in first.stdout
    assert "orphan folders (no job record; kept): 1: inputs/orphan" in first.stdout
    [aside] = environment.data_dir.glob("jobs.db.corrupt-*")
    assert aside.read_bytes() == garbage and (environment.data_dir / "inputs" / "orphan").is_dir()
    second = recover()  # nothing more to do
    assert second.returncode == 0 and "restored: 0" in second.stdout and "moved aside (unreadable): 0" in second.stdout

    store = environment.store()
    for job_id, job in before.items():
        rebuilt = store.get(job_id)
        assert rebuilt is not None and rebuilt.tenant == "alice"
        assert (rebuilt.state, rebuilt.result, rebuilt.input_key) == (job.state, job.result, job.input_key)


def test_a_worker_that_cannot_record_its_result_keeps_it_and_retries(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, heartbeat_s=0.5)
    server = environment.serve(workers=0)
    database = environment.data_dir / "jobs.db"
    away = environment.data_dir / "jobs.db.away"
    worker = None
    try:
        job = submit(server, 25, SECONDS_OPTIONS)
        worker = environment.worker()
        server.wait_for_job(job["id"], lambda j: j["state"] == "running" and j["progress"]["iteration"] > 0, 60,
                            "to be training", logs=(worker.log,))
        # The store becomes unusable (the file cannot be opened: no connection gets in) until we put it back.
        database.rename(away)
        database.mkdir()
        try:
            assert server.client.get("/v1/jobs").status_code == 503
            wait_until(lambda: "its result not recorded yet" in worker.log.read_text(), 120,
                       "the worker to fail to record its result", logs=(worker.log,))
            kept = json.loads((environment.data_dir / "artifacts" / job["id"] / "job.json").read_text())
            assert kept["state"] == "succeeded" and worker.alive()
        finally:
            database.rmdir()
            away.rename(database)
        done = server.wait_finished(job["id"], timeout=30, logs=(worker.log,))
        assert done["state"] == "succeeded" and done["result"]["artifacts"] == kept["result"]["artifacts"]
        assert server.stored(job["id"]).attempts == 1  # recorded, not run again
        assert "Unhandled exception" not in worker.log.read_text()
    finally:
        if worker is not None:
            worker.stop()
        server.stop()


# ---------------------------------------------------------------------------------------------- farm (Redis)


def test_job_records_flushed_from_redis_are_rebuilt(tmp_path: Path) -> None:
    redis_process, url = redis_server(tmp_path)
    environment = BcfEnvironment(tmp_path, queue_url=url, heartbeat_s=0.5, stale_after_s=3)
    server = environment.serve()
    worker = environment.worker()
    try:
        job = submit(server, 26, TINY_OPTIONS)
        done = server.wait_finished(job["id"], logs=(worker.log,))
        assert done["state"] == "succeeded", done["error"]
        redis.Redis.from_url(url).flushdb()  # records, indexes and queue: all gone
        assert server.client.get(f"/v1/jobs/{job['id']}").status_code == 404
        # The worker's next recovery pass (every second here) sees the store lost its records and rebuilds them.
        back = wait_until(lambda: server.client.get(f"/v1/jobs/{job['id']}").json().get("state"), 30,
                          "the record to be rebuilt", logs=(worker.log,))
        assert back == "succeeded" and server.job(job["id"])["result"] == done["result"]
        again = server.client.post("/v1/jobs", files=tiny_material(26), data={"options": json.dumps(TINY_OPTIONS)})
        assert again.status_code == 200 and again.json()["id"] == job["id"]
        later = submit(server, 27, TINY_OPTIONS)  # the queue works after the flush
        assert server.wait_finished(later["id"], logs=(worker.log,))["state"] == "succeeded"
    finally:
        worker.stop()
        server.stop()
        redis_process.stop()


# ------------------------------------------------------------------------------- the rebuild, without processes


def test_rebuild_and_recovery_passes_trust_what_the_data_folder_holds(tmp_path: Path) -> None:
    """A stale running job whose result is complete on disk is recorded as succeeded, not run again; a record
    whose result files are gone comes back failed; records of jobs stored before records were kept as files are
    written beside their files by the first rebuild."""
    queue = JobQueue(Settings(_env_file=None, data_dir=tmp_path, stale_after_s=1))
    long_ago = utc_now() - datetime.timedelta(hours=1)
    finished, lost, older = a_job(), a_job(), a_job()
    for job in (finished, lost, older):
        (queue.inputs_path(job.id) / "albedo").mkdir(parents=True)
    # `finished`: running, its worker gone, its result complete with its record (the worker could not record it).
    running = finished.model_copy(update={"state": "running", "worker": "gone", "attempts": 1,
                                          "heartbeat_at": long_ago, "updated_at": long_ago})
    queue.store.restore(running)
    result = JobResult(psnr=40.0, ssim=0.99, size_bytes=10, bits_per_texel=1.0, artifacts=["decoder.bin"])
    queue.artifacts_path(finished.id).mkdir(parents=True)
    (queue.artifacts_path(finished.id) / "decoder.bin").write_bytes(b"0123456789")
    write_record(queue.artifacts_path(finished.id), running.ended("succeeded", result=result))
    # `lost`: only its inputs' record, saying succeeded, and no result files.
    write_record(queue.inputs_path(lost.id), lost.ended("succeeded", result=result))
    # `older`: in the store, with no record beside its files.
    queue.store.restore(older)

    [recovered] = queue.recover()
    assert recovered.id == finished.id and recovered.state == "succeeded" and recovered.result == result
    report = queue.rebuild()
    assert report.restored == [f"{lost.id} failed"] and report.requeued == [] and report.orphans == []
    assert "result files were lost" in (queue.store.get(lost.id).error or "")
    assert report.kept == [older.id] and read_record(queue.inputs_path(older.id)) == older
    assert queue.rebuild().model_dump() == RecoveryReport().model_dump()  # nothing more to do
