"""Farm mode without a shared file system: the API and two workers, each with a data folder of its own, share a
real redis-server (BCF_QUEUE_URL) and a real S3-compatible server, `rclone serve s3` (BCF_STORAGE_URL)."""

from __future__ import annotations

import io
import json
import signal
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import pytest
import redis

from bcf.core import load_export
from service_harness import (TINY_OPTIONS, BcfEnvironment, Process, S3Server, Server, redis_server, tiny_material,
                             wait_until)

FAST_RECOVERY = {"heartbeat_s": 0.5, "stale_after_s": 3, "max_attempts": 2, "storage_timeout_s": 2,
                 "storage_retries": 2}


@dataclass
class Farm:
    s3: S3Server
    api: Server
    api_env: BcfEnvironment
    workers: list[Process]
    redis_url: str

    def job_folder(self, kind: str, job_id: str) -> Path:
        """Where the S3 server keeps the job's objects (its bucket is a folder)."""
        return self.s3.folder / self.s3.bucket / "jobs" / kind / job_id

    def submit(self, variant: int) -> str:
        response = self.api.client.post("/v1/jobs", files=tiny_material(variant),
                                        data={"options": json.dumps(TINY_OPTIONS)})
        assert response.status_code == 202, response.text
        return response.json()["id"]


def _environment(root: Path, s3: S3Server, redis_url: str) -> BcfEnvironment:
    root.mkdir()
    environment = BcfEnvironment(root, queue_url=redis_url, **FAST_RECOVERY)
    environment.env.update(s3.client_env())
    return environment


@pytest.fixture
def farm(tmp_path: Path) -> Iterator[Farm]:
    redis, url = redis_server(tmp_path)
    s3 = S3Server(tmp_path)
    api_env = _environment(tmp_path / "api", s3, url)
    api = api_env.serve()
    workers = [_environment(tmp_path / f"worker{n}", s3, url).worker() for n in (1, 2)]
    yield Farm(s3, api, api_env, workers, url)
    for process in [*workers, api, s3, redis]:
        process.stop()


def _download(farm: Farm, job_id: str, folder: Path) -> Path:
    archive = farm.api.client.get(f"/v1/jobs/{job_id}/artifacts")
    assert archive.status_code == 200, archive.text
    with zipfile.ZipFile(io.BytesIO(archive.content)) as z:
        z.extractall(folder)
    return folder


def test_jobs_run_on_workers_without_a_shared_folder_through_object_storage(farm: Farm, tmp_path: Path) -> None:
    submitted = [farm.submit(30 + variant) for variant in range(4)]
    logs = tuple(w.log for w in farm.workers)
    finished = [farm.api.wait_finished(job_id, timeout=180, logs=logs) for job_id in submitted]
    assert [j["state"] for j in finished] == ["succeeded"] * 4, [j["error"] for j in finished]
    assert len({farm.api.stored(job_id).worker for job_id in submitted}) == 2  # both workers took jobs

    job_id = submitted[0]
    exported = load_export(_download(farm, job_id, tmp_path / "result"))
    assert exported.manifest.material.name == finished[0]["name"]
    report = farm.api.client.get(f"/v1/jobs/{job_id}/report")
    assert report.status_code == 200 and report.json()["aggregate"]["psnr"]["all"] == finished[0]["result"]["psnr"]
    one = farm.api.client.get(f"/v1/jobs/{job_id}/artifacts/manifest.json")
    assert one.status_code == 200 and one.headers["content-type"] == "application/json"
    assert one.content == (tmp_path / "result" / "manifest.json").read_bytes()

    # The result is committed in the bucket; no data folder holds it, and the inputs left the bucket when the
    # job ended (only their record stays).
    assert (farm.job_folder("artifacts", job_id) / "COMMITTED.json").is_file()
    assert sorted(p.name for p in farm.job_folder("inputs", job_id).rglob("*") if p.is_file()) == ["job.json"]
    for environment_root in (farm.api_env.root, *(w.log.parent for w in farm.workers)):
        leftover = [p for p in (environment_root / "data" / "artifacts").rglob("*") if p.is_file()]
        assert leftover == [], leftover

    # Redis flushed: the workers' recovery pass rebuilds the records from the bucket (no data folder has them).
    redis.Redis.from_url(farm.redis_url).flushdb()
    assert farm.api.client.get(f"/v1/jobs/{job_id}").status_code == 404
    for before in finished:
        answer = wait_until(lambda: (r := farm.api.client.get(f"/v1/jobs/{before['id']}")).status_code == 200 and r,
                            60, f"job {before['id']} to be restored", logs=tuple(w.log for w in farm.workers))
        assert answer.json()["state"] == "succeeded" and answer.json()["result"] == before["result"]
    assert load_export(_download(farm, job_id, tmp_path / "again")).manifest == exported.manifest

    purged = farm.api.client.delete(f"/v1/jobs/{job_id}", params={"purge": "true"})
    assert purged.status_code == 200 and purged.json()["purged_at"]
    assert not any(p.is_file() for p in farm.job_folder("artifacts", job_id).rglob("*"))


def test_a_worker_killed_while_uploading_leaves_no_result_and_the_job_finishes_on_retry(farm: Farm,
                                                                                     tmp_path: Path) -> None:
    job_id = farm.submit(40)
    farm.s3.bandwidth("20k")  # a slow store: the upload of the result takes seconds

    def uploading() -> Process | None:
        started = [w for w in farm.workers if f"job {job_id}: uploading" in w.log.read_text(errors="replace")]
        attempts = list(farm.job_folder("artifacts", job_id).glob("attempt-*"))
        return started[0] if started and attempts and any(p.is_file() for p in attempts[0].rglob("*")) else None

    uploader = wait_until(uploading, 120, "the result upload to start", interval=0.05,
                          logs=tuple(w.log for w in farm.workers))
    uploader.stop(signal.SIGKILL)
    # Some objects of the attempt are in the bucket, but no commit marker: nothing is served.
    assert not (farm.job_folder("artifacts", job_id) / "COMMITTED.json").exists()
    assert farm.api.job(job_id)["state"] == "running"
    assert farm.api.client.get(f"/v1/jobs/{job_id}/report").status_code == 409

    farm.s3.bandwidth("off")
    other = next(w for w in farm.workers if w is not uploader)
    done = farm.api.wait_finished(job_id, timeout=180, logs=(other.log,))
    assert done["state"] == "succeeded", done["error"]
    stored = farm.api.stored(job_id)
    assert stored.attempts == 2 and stored.worker is not None and str(other.popen.pid) in stored.worker
    load_export(_download(farm, job_id, tmp_path / "result"))
    # The killed attempt's objects are gone: only the committed attempt and its marker remain.
    assert len(list(farm.job_folder("artifacts", job_id).glob("attempt-*"))) == 1


def test_object_storage_down_fails_the_job_clearly_after_its_attempts(farm: Farm) -> None:
    job_id = farm.submit(50)
    farm.s3.stop()
    done = farm.api.wait_finished(job_id, timeout=180, logs=tuple(w.log for w in farm.workers))
    assert done["state"] == "failed"
    assert "gave up after 2 attempts" in done["error"] and "object storage s3://bcf/jobs" in done["error"]
    assert farm.api.stored(job_id).attempts == 2
    refused = farm.api.client.post("/v1/jobs", files=tiny_material(51), data={"options": json.dumps(TINY_OPTIONS)})
    assert refused.status_code == 503 and "object storage unavailable" in refused.json()["detail"]
