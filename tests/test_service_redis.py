"""Farm mode: the API and two worker processes share a real redis-server (BCF_QUEUE_URL)."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import pytest

from bcf.core import load_export
from service_harness import TINY_OPTIONS, BcfEnvironment, material_zip, redis_server, tiny_material


@pytest.fixture(scope="module")
def farm(tmp_path_factory: pytest.TempPathFactory) -> Any:
    root = tmp_path_factory.mktemp("farm")
    redis, url = redis_server(root)
    environment = BcfEnvironment(root, queue_url=url, heartbeat_s=0.5)
    server = environment.serve()  # farm mode: no worker processes by default
    workers = [environment.worker(), environment.worker()]
    yield environment, server, workers
    for worker in workers:
        worker.stop()
    server.stop()
    redis.stop()


def test_jobs_submitted_to_the_api_run_on_both_workers_through_redis(farm: Any, tmp_path: Path) -> None:
    environment, server, workers = farm
    assert server.client.get("/healthz").json()["mode"] == "farm"
    # Nothing of the queue lives in the data directory in farm mode: only inputs and artifacts.
    assert not (environment.data_dir / "jobs.db").exists() and not (environment.data_dir / "queue.db").exists()
    submitted = []
    for variant in range(6):
        files = tiny_material(10 + variant)
        if variant % 2:  # half of them as a zip of the material folder
            response = server.client.post("/v1/jobs", files={"material": ("set.zip", material_zip(files),
                                                                          "application/zip")},
                                          data={"options": json.dumps(TINY_OPTIONS)})
        else:
            response = server.client.post("/v1/jobs", files=files, data={"options": json.dumps(TINY_OPTIONS)})
        assert response.status_code == 202, response.text
        submitted.append(response.json()["id"])
    logs = tuple(w.log for w in workers)
    finished = [server.wait_finished(job_id, timeout=180, logs=logs) for job_id in submitted]
    assert [j["state"] for j in finished] == ["succeeded"] * 6, [j["error"] for j in finished]
    stored = [server.stored(job_id) for job_id in submitted]  # the API does not show who ran a job: the store does
    assert len({j.worker for j in stored}) == 2  # both workers took jobs
    assert all(j.attempts == 1 for j in stored)

    listed = server.client.get("/v1/jobs", params={"state": "succeeded", "limit": 4}).json()
    assert listed["total"] == 6 and len(listed["jobs"]) == 4
    assert [j["id"] for j in listed["jobs"]] == submitted[::-1][:4]  # newest first
    page2 = server.client.get("/v1/jobs", params={"state": "succeeded", "limit": 4, "offset": 4}).json()
    assert [j["id"] for j in page2["jobs"]] == submitted[::-1][4:]

    archive = server.client.get(f"/v1/jobs/{submitted[1]}/artifacts")
    assert archive.status_code == 200
    with zipfile.ZipFile(io.BytesIO(archive.content)) as z:
        z.extractall(tmp_path / "result")
    exported = load_export(tmp_path / "result")
    assert exported.manifest.material.name == "Chainmail004_1K-PNG"  # the zip's folder

    metrics = server.client.get("/metrics").text
    assert 'bcf_jobs{state="succeeded"} 6' in metrics and "bcf_queue_depth 0" in metrics
    assert 'bcf_job_duration_seconds_count{state="succeeded"} 6' in metrics
