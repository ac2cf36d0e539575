"""Disk space and retention (issue 16, case 5), with real servers, workers and file systems: the free-space
floor (507 before an upload is read), a disk that fills while an upload is stored (507 JSON, never a plain 500),
inputs removed once a job ends, `DELETE /v1/jobs/{id}?purge=true`, and BCF_RETENTION_DAYS, in the embedded and
the Redis mode."""

from __future__ import annotations

import datetime
import json
import re
import shutil
from pathlib import Path

import httpx
import pytest
from pydantic import ValidationError

from bcf.jobs.settings import Settings
from service_harness import TINY_OPTIONS, BcfEnvironment, Server, redis_server, tiny_material

ENDLESS_OPTIONS = {"preset": "fast", "phase1_iterations": 1_000_000, "phase2_iterations": 10, "batch_size": 1024}
# The workers' recovery pass, which expires old jobs, runs every max(1 s, BCF_STALE_AFTER_S / 3).
QUICK_PASSES = {"heartbeat_s": 0.5, "stale_after_s": 3, "retention_days": 1}


def submit(server: Server, files: dict, options: dict) -> httpx.Response:
    return server.client.post("/v1/jobs", files=files, data={"options": json.dumps(options)})


def assert_json_error(response: httpx.Response, status: int, *words: str) -> str:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json"), response.headers
    detail = response.json()["detail"]
    assert all(word.lower() in detail.lower() for word in words), detail
    return detail


def metric(server: Server, name: str) -> float:
    text = server.client.get("/metrics").text
    found = re.search(rf"^{re.escape(name)} (\S+)$", text, re.M)
    assert found, f"{name} not in /metrics:\n{text}"
    return float(found.group(1))


def files_of(environment: BcfEnvironment, job_id: str) -> dict[str, bool]:
    """Whether the job still has input images, and an artifacts folder. Its inputs folder keeps the record
    (job.json) after the images go: a lost job store is rebuilt from it."""
    inputs = environment.data_dir / "inputs" / job_id
    images = inputs.is_dir() and any(p.name != "job.json" for p in inputs.iterdir())
    return {"inputs": images, "artifacts": (environment.data_dir / "artifacts" / job_id).exists()}


def test_an_upload_below_the_disk_floor_is_507_before_it_is_read(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, min_free_disk_mb=2**40)  # a floor above any disk's free space
    server = environment.serve(workers=0)
    try:
        detail = assert_json_error(submit(server, tiny_material(0), TINY_OPTIONS), 507, "BCF_MIN_FREE_DISK_MB")
        assert "MiB free" in detail
        assert [p for p in environment.data_dir.rglob("*") if p.parent.name in ("inputs", "uploads")] == []
        assert server.client.get("/v1/jobs").json()["total"] == 0  # reads go on
        ready = httpx.get(server.url + "/readyz")
        assert ready.status_code == 503 and ready.json()["disk"] == "low" and ready.json()["store"] == "ok"
        assert metric(server, 'bcf_uploads_refused_total{reason="disk"}') == 1
        assert metric(server, "bcf_disk_min_free_bytes") == 2**60
        assert 0 < metric(server, "bcf_disk_free_bytes") < 2**60
    finally:
        server.stop()


def test_a_disk_that_fills_while_uploads_are_stored_answers_507_json(tmp_path: Path) -> None:
    """The data directory on a 512 KiB tmpfs of the server's own (a user and mount namespace: no root needed,
    nothing left mounted), no floor: uploads fill it until one finds no room, in the staging folder, the job
    database or the queue database. That one is a 507 with a JSON detail; reads still answer."""
    assert shutil.which("unshare"), "unshare (util-linux) is required"
    environment = BcfEnvironment(tmp_path, min_free_disk_mb=0)
    on_tmpfs = ("unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                'mkdir -p "$0" && mount -t tmpfs -o size=512k bcf-test "$0" && exec "$@"', str(environment.data_dir))
    server = environment.serve(workers=0, wrapper=on_tmpfs)
    try:
        answers = [submit(server, tiny_material(variant, 128), TINY_OPTIONS) for variant in range(12)]
        statuses = [a.status_code for a in answers]
        assert statuses[0] == 202 and 507 in statuses and set(statuses) <= {202, 507}, statuses
        for refused in (a for a in answers if a.status_code == 507):
            assert_json_error(refused, 507, "disk", "full")
        listed = server.client.get("/v1/jobs")
        assert listed.status_code == 200 and listed.json()["total"] == statuses.count(202)
        assert httpx.get(server.url + "/healthz").status_code == 200
        assert metric(server, 'bcf_uploads_refused_total{reason="disk"}') == statuses.count(507)
    finally:
        server.stop()
    assert "Traceback" not in server.log.read_text(errors="replace")


def purge_and_expire(environment: BcfEnvironment, server: Server, variant: int) -> None:
    """A succeeded job without its inputs; purged: a tombstone whose results answer 410 and whose material may
    be submitted again; that new job, finished "two days ago", expired by the workers (BCF_RETENTION_DAYS=1)."""
    purged_before = metric(server, "bcf_jobs_purged")
    job = submit(server, tiny_material(variant), TINY_OPTIONS).json()
    done = server.wait_finished(job["id"])
    assert done["state"] == "succeeded", done["error"]
    assert files_of(environment, job["id"]) == {"inputs": False, "artifacts": True}

    purged = server.client.delete(f"/v1/jobs/{job['id']}", params={"purge": "true"})
    assert purged.status_code == 200, purged.text
    tombstone = purged.json()
    assert tombstone["state"] == "succeeded" and tombstone["purged_at"] is not None
    assert tombstone["result"]["psnr"] == done["result"]["psnr"] and tombstone["result"]["artifacts"] == []
    assert files_of(environment, job["id"]) == {"inputs": False, "artifacts": False}
    for suffix in ("report", "artifacts", "artifacts/report.json"):
        assert_json_error(server.client.get(f"/v1/jobs/{job['id']}/{suffix}"), 410, "removed", job["id"])
    assert server.client.delete(f"/v1/jobs/{job['id']}", params={"purge": "true"}).status_code == 200  # again: same

    again = submit(server, tiny_material(variant), TINY_OPTIONS)  # a tombstone holds no results to hand out
    assert again.status_code == 202 and again.json()["id"] != job["id"], again.text
    rerun = server.wait_finished(again.json()["id"])
    assert rerun["state"] == "succeeded" and rerun["purged_at"] is None
    long_ago = datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(days=2)
    environment.store().update(rerun["id"], lambda j: j.model_copy(update={"finished_at": long_ago}))
    expired = server.wait_for_job(rerun["id"], lambda j: j["purged_at"] is not None, 30, "to expire")
    assert expired["state"] == "succeeded" and expired["result"]["artifacts"] == []
    assert files_of(environment, rerun["id"]) == {"inputs": False, "artifacts": False}
    assert metric(server, "bcf_jobs_purged") == purged_before + 2


def test_ended_jobs_lose_their_inputs_and_finished_ones_are_purged_or_expire(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, **QUICK_PASSES)
    server = environment.serve(workers=1)
    try:
        running = submit(server, tiny_material(1), ENDLESS_OPTIONS).json()
        server.wait_for_job(running["id"], lambda j: j["progress"]["stage"] == "training", 120, "to train")
        queued = submit(server, tiny_material(2), ENDLESS_OPTIONS).json()  # the one worker is busy
        assert files_of(environment, queued["id"])["inputs"]
        cancelled = server.client.delete(f"/v1/jobs/{queued['id']}")
        assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled", cancelled.text
        assert files_of(environment, queued["id"]) == {"inputs": False, "artifacts": False}
        waiting = submit(server, tiny_material(5), ENDLESS_OPTIONS).json()
        purged = server.client.delete(f"/v1/jobs/{waiting['id']}", params={"purge": "true"})  # cancelled, purged
        assert purged.status_code == 200 and purged.json()["state"] == "cancelled", purged.text
        assert purged.json()["purged_at"] is not None and not files_of(environment, waiting["id"])["inputs"]

        assert_json_error(server.client.delete(f"/v1/jobs/{running['id']}", params={"purge": "true"}), 409,
                          "running", "cancel")
        assert server.client.delete(f"/v1/jobs/{running['id']}").status_code == 202
        assert server.wait_finished(running["id"])["state"] == "cancelled"
        assert not files_of(environment, running["id"])["inputs"]

        purge_and_expire(environment, server, variant=3)
    finally:
        server.stop()


def test_purge_and_retention_in_farm_mode(tmp_path: Path) -> None:
    redis, url = redis_server(tmp_path)
    environment = BcfEnvironment(tmp_path, queue_url=url, **QUICK_PASSES)
    server = environment.serve()
    worker = environment.worker()
    try:
        purge_and_expire(environment, server, variant=4)
    finally:
        worker.stop()
        server.stop()
        redis.stop()


@pytest.mark.parametrize("days", ["0", "-1", "soon"])
def test_a_retention_that_is_not_a_positive_number_is_refused(days: str, tmp_path: Path) -> None:
    with pytest.raises(ValidationError, match="retention_days"):
        Settings(_env_file=None, data_dir=tmp_path, retention_days=days)
    assert Settings(_env_file=None, data_dir=tmp_path).retention_days is None

