"""The service in embedded mode, end to end with real processes: `bcf serve` (uvicorn on 127.0.0.1) and
`bcf worker` processes sharing a SQLite queue in a data directory."""

from __future__ import annotations

import datetime
import io
import json
import os
import signal
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import pytest

from bcf.core import load_export
from bcf.core.codec import bc6h
from bcf.core.codec import containers
from bcf_command import run_bcf
from crafted_images import png_claiming
from reference_decoders import decode_with_oiio
from service_harness import TINY_OPTIONS, BcfEnvironment, tiny_material, wait_until

# Long enough to be caught running; stopped by cancel or by a killed worker (never run to the end).
ENDLESS_OPTIONS = {"preset": "fast", "phase1_iterations": 1_000_000, "phase2_iterations": 10, "batch_size": 1024}
# About 10 s of training on 64x64: a worker can be killed in the middle and the job still finish soon after.
KILLABLE_OPTIONS = {"preset": "fast", "phase1_iterations": 1500, "phase2_iterations": 1500, "batch_size": 1024}


def submit(server: Any, files: dict, options: dict) -> Any:
    return server.client.post("/v1/jobs", files=files, data={"options": json.dumps(options)})


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """An embedded service with one worker process started by `bcf serve` itself."""
    environment = BcfEnvironment(tmp_path_factory.mktemp("embedded"), heartbeat_s=0.5)
    server = environment.serve(workers=1)
    yield server
    server.stop()


def test_submit_poll_download_and_decode_the_artifacts(service: Any, tmp_path: Path) -> None:
    response = submit(service, tiny_material(1), TINY_OPTIONS)
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["state"] == "queued" and response.headers["location"] == f"/v1/jobs/{job['id']}"
    assert {f["role"] for f in job["inputs"]} == {"albedo", "normal", "roughness", "metalness"}
    assert job["options"]["normal_convention"] == "directx"  # from ambientCG's plain _Normal name

    done = service.wait_finished(job["id"])
    assert done["state"] == "succeeded", done["error"]
    assert done["progress"]["stage"] == "finished" and service.stored(job["id"]).attempts == 1
    # The worker ran the API's own queue message, not one a recovery pass re-sent after BCF_STALE_AFTER_S (30 s).
    waited = datetime.datetime.fromisoformat(done["started_at"]) - datetime.datetime.fromisoformat(done["created_at"])
    assert waited.total_seconds() < 15, waited
    assert done["progress"]["phase"] == 2 and done["progress"]["iteration"] == TINY_OPTIONS["phase2_iterations"]

    archive = service.client.get(f"/v1/jobs/{job['id']}/artifacts")
    assert archive.status_code == 200 and archive.headers["content-type"] == "application/zip"
    folder = tmp_path / "result"
    with zipfile.ZipFile(io.BytesIO(archive.content)) as z:
        assert sorted(z.namelist()) == sorted(done["result"]["artifacts"])
        z.extractall(folder)
    # The export loads (it checks every file against the manifest's SHA-256) and scores what the job said.
    exported = load_export(folder)
    report = json.loads((folder / "report.json").read_text())
    assert report["aggregate"]["psnr"]["all"] == pytest.approx(done["result"]["psnr"])
    assert exported.manifest.material.name == done["name"]
    # An independent BC6H decoder (OpenImageIO) reads the downloaded features as our decoder does.
    texture = containers.read_dds(folder / "features_0.dds")
    for level in range(len(texture.levels)):
        ours = bc6h.decode_image(texture.levels[level], *texture.level_size(level), texture.signed)
        by_oiio = decode_with_oiio(folder / "features_0.dds", level)
        assert np.array_equal(ours.view(np.uint16), by_oiio.view(np.uint16)), level
    decoded = run_bcf("decode", folder, "-o", tmp_path / "decoded")
    assert decoded.returncode == 0, decoded.stderr
    assert (tmp_path / "decoded" / "albedo.png").is_file()

    single = service.client.get(f"/v1/jobs/{job['id']}/artifacts/report.json")
    assert single.status_code == 200 and single.json() == report
    assert service.client.get(f"/v1/jobs/{job['id']}/report").json() == report

    again = submit(service, tiny_material(1), TINY_OPTIONS)
    assert again.status_code == 200 and again.json()["id"] == job["id"]  # same inputs + options: same job
    # Other options are another job; baselines are scored and shipped as for `bcf compress --baselines`.
    other = submit(service, tiny_material(1), {**TINY_OPTIONS, "seed": 1, "baselines": ["bc1_bc5_half", "naive"]})
    assert other.status_code == 202 and other.json()["id"] != job["id"]
    assert other.json()["options"]["baselines"] == ["bc1_bc5_half", "naive_bc6"]
    finished = service.wait_finished(other.json()["id"])
    assert finished["state"] == "succeeded", finished["error"]
    assert "baselines/bc1_bc5_half/albedo.dds" in finished["result"]["artifacts"]
    scored = service.client.get(f"/v1/jobs/{finished['id']}/report").json()["baselines"]
    assert set(scored) == {"bc1_bc5_half", "naive_bc6"}


def test_the_api_reads_headers_only_and_a_file_that_does_not_decode_fails_its_job(service: Any) -> None:
    """Pixels are decoded by the worker, not the API: a PNG whose header is sound but whose data stops after one
    row is accepted (202), and its job fails with a message naming the file as the client sent it."""
    files = tiny_material(7)
    files["albedo"] = ("broken_Color.png", png_claiming(64, 64, padding=4096), "image/png")
    response = submit(service, files, TINY_OPTIONS)
    assert response.status_code == 202, response.text
    done = service.wait_finished(response.json()["id"])
    assert done["state"] == "failed" and "broken_Color.png" in done["error"], done
    assert "Traceback" not in done["error"] and "/" not in done["error"].split("broken_Color.png")[0]


def test_what_the_worker_finds_in_the_pixels_joins_the_jobs_notes(service: Any, tmp_path: Path) -> None:
    """An EXR albedo: the API notes from its header that it is linear; the worker, decoding it, that values
    above 1 were clipped."""
    files = tiny_material(9)
    bright = np.full((64, 64, 3), 1.5, dtype=np.float32)
    image = oiio.ImageBuf(oiio.ImageSpec(64, 64, 3, oiio.HALF))
    image.set_pixels(oiio.ROI(0, 64, 0, 64), bright)
    assert image.write(str(tmp_path / "bright.exr")), image.geterror()
    files["albedo"] = ("bright_Color.exr", (tmp_path / "bright.exr").read_bytes(), "image/x-exr")
    response = submit(service, files, TINY_OPTIONS)
    assert response.status_code == 202, response.text
    assert any("linear" in note for note in response.json()["notes"])
    assert not any("clipped" in note for note in response.json()["notes"])  # no pixel decoded yet
    done = service.wait_finished(response.json()["id"])
    assert done["state"] == "succeeded", done["error"]
    assert any("bright_Color.exr" in note and "12288 values outside [0, 1] clipped" in note for note in done["notes"])


def test_a_job_past_the_wall_clock_limit_stops_and_fails(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, heartbeat_s=0.5, job_time_limit_s=3)
    server = environment.serve(workers=1)
    try:
        response = submit(server, tiny_material(8), ENDLESS_OPTIONS)
        assert response.status_code == 202, response.text
        done = server.wait_finished(response.json()["id"], timeout=120)
        assert done["state"] == "failed" and "BCF_JOB_TIME_LIMIT_S" in done["error"], done
        assert done["progress"]["iteration"] < ENDLESS_OPTIONS["phase1_iterations"]
        assert server.stored(done["id"]).attempts == 1  # a limit is not a crash: no second run
    finally:
        server.stop()


def test_without_tokens_the_server_listens_on_loopback_only(tmp_path: Path) -> None:
    server = BcfEnvironment(tmp_path).serve(None, 0, "--host", "0.0.0.0")
    try:
        log = server.log.read_text()
        assert "no BCF_API_TOKENS configured: listening on 127.0.0.1 only, not 0.0.0.0" in log
        assert f"Uvicorn running on {server.url}" in log
        assert server.client.get("/v1/jobs").json()["total"] == 0  # no token needed
    finally:
        server.stop()


def test_cancelling_a_running_job_stops_it_within_seconds(service: Any) -> None:
    job = submit(service, tiny_material(2), ENDLESS_OPTIONS).json()
    running = service.wait_for_job(job["id"], lambda j: j["state"] == "running" and j["progress"]["iteration"] > 0,
                                   60, "to be training")
    assert running["progress"]["total"] == ENDLESS_OPTIONS["phase1_iterations"]
    assert running["progress"]["eta_s"] > 0 and running["progress"]["psnr"] is not None
    response = service.client.delete(f"/v1/jobs/{job['id']}")
    assert response.status_code == 202 and response.json()["state"] == "running"
    assert service.stored(job["id"]).cancel_requested
    cancelled = service.wait_for_job(job["id"], lambda j: j["state"] == "cancelled", 10, "to be cancelled")
    assert cancelled["progress"]["iteration"] < ENDLESS_OPTIONS["phase1_iterations"]
    assert service.client.get(f"/v1/jobs/{job['id']}/artifacts").status_code == 409
    # The worker is free again: the next job runs.
    follow = submit(service, tiny_material(3), TINY_OPTIONS).json()
    assert service.wait_finished(follow["id"])["state"] == "succeeded"


def test_a_queued_job_survives_a_server_restart(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path)
    server = environment.serve(workers=0)  # no worker: the job stays queued
    job = submit(server, tiny_material(4), TINY_OPTIONS).json()
    assert server.stop() == 0

    server = environment.serve(workers=0)
    try:
        assert server.job(job["id"])["state"] == "queued"
        listed = server.client.get("/v1/jobs", params={"state": "queued"}).json()
        assert [j["id"] for j in listed["jobs"]] == [job["id"]]
        worker = environment.worker()
        try:
            assert server.wait_finished(job["id"], logs=(worker.log,))["state"] == "succeeded"
        finally:
            worker.stop()
    finally:
        server.stop()


def test_a_job_whose_worker_is_killed_is_rerun_by_the_next_worker(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, heartbeat_s=0.5, stale_after_s=3)
    server = environment.serve(workers=0)
    try:
        job = submit(server, tiny_material(5), KILLABLE_OPTIONS).json()
        first = environment.worker()
        server.wait_for_job(job["id"], lambda j: j["state"] == "running" and j["progress"]["iteration"] > 0, 60,
                            "to be training", logs=(first.log,))
        first.stop(signal.SIGKILL)
        assert server.job(job["id"])["state"] == "running"  # nobody knows yet that its worker is gone

        second = environment.worker()
        try:
            done = server.wait_finished(job["id"], timeout=120, logs=(second.log,))
        finally:
            second.stop()
        assert done["state"] == "succeeded", done["error"]
        assert server.stored(job["id"]).attempts == 2 and done["error"] is None
        assert "recovered" in second.log.read_text()
        # The killed attempt's staging folder is gone; only the finished artifacts remain.
        assert [p.name for p in (environment.data_dir / "artifacts").iterdir()] == [job["id"]]
    finally:
        server.stop()


@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_stopped_worker_puts_its_job_back_at_once(stop_signal: int, tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path, heartbeat_s=0.5)
    server = environment.serve(workers=0)
    try:
        job = submit(server, tiny_material(6), ENDLESS_OPTIONS).json()
        worker = environment.worker()
        server.wait_for_job(job["id"], lambda j: j["state"] == "running", 60, "to be running", logs=(worker.log,))
        assert worker.stop(stop_signal, timeout=30) == 0
        back = server.stored(job["id"])
        assert back.state == "queued" and back.worker is None and back.attempts == 1
        assert "back in the queue" in worker.log.read_text()
        assert server.client.delete(f"/v1/jobs/{job['id']}").json()["state"] == "cancelled"
    finally:
        server.stop()


def _children(pid: int) -> list[int]:
    """Running processes whose parent is `pid`, from /proc."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            state, parent = stat.read_text().rsplit(")", 1)[1].split()[:2]
        except (OSError, IndexError, ValueError):
            continue  # ended while listed
        if int(parent) == pid and state != "Z":
            found.append(int(stat.parent.name))
    return found


def _ended(pid: int) -> bool:
    """Gone, or a zombie nobody reaped (a container's PID 1 may not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def test_a_killed_worker_is_replaced_and_workers_end_with_their_server(tmp_path: Path) -> None:
    """kill -9 of the worker `bcf serve` started: reaped, replaced (readiness and /metrics count it), and the
    replacement takes jobs; kill -9 of `bcf serve` then ends its worker too (issue 16, case 2)."""
    environment = BcfEnvironment(tmp_path, heartbeat_s=0.5)
    server = environment.serve(workers=1)
    try:
        readiness = server.client.get("/readyz")
        assert readiness.status_code == 200, readiness.text
        assert readiness.json()["store"] == "ok" and readiness.json()["disk_free_bytes"] > 0
        wait_until(lambda: len(_children(server.popen.pid)) == 1, 30, "the worker to start", logs=(server.log,))
        [first] = _children(server.popen.pid)
        os.kill(first, signal.SIGKILL)
        wait_until(lambda: server.client.get("/readyz").json()["workers"] == {"wanted": 1, "live": 1, "restarts": 1},
                   30, "a replacement worker", logs=(server.log,))
        [second] = _children(server.popen.pid)
        assert second != first and _ended(first)
        assert f"worker pid {first} exited with code -9" in server.log.read_text()
        assert "bcf_worker_restarts_total 1" in server.client.get("/metrics").text
        job = submit(server, tiny_material(7), TINY_OPTIONS).json()
        assert server.wait_finished(job["id"], timeout=120, logs=(server.log,))["state"] == "succeeded"
    finally:
        server.stop(signal.SIGKILL)
    wait_until(lambda: _ended(second), 30, "the worker to end with its server", logs=(server.log,))


def test_tenants_see_only_their_own_jobs_and_the_admin_sees_all(tmp_path: Path) -> None:
    """Named tokens: another tenant's job is a 404 for reading, listing, downloading and cancelling; the same
    files from two tenants are two jobs (deduplication tells nobody what another submitted); the admin token
    sees both (issue 16, case 6)."""
    environment = BcfEnvironment(tmp_path, api_tokens="alice:a-token,bob:b-token", admin_token="root-token")
    server = environment.serve(workers=0)
    as_ = {name: {"Authorization": f"Bearer {token}"}
           for name, token in (("alice", "a-token"), ("bob", "b-token"), ("admin", "root-token"))}
    try:
        files = tiny_material(8)
        data = {"options": json.dumps(TINY_OPTIONS)}
        alice = server.client.post("/v1/jobs", files=files, data=data, headers=as_["alice"])
        assert alice.status_code == 202, alice.text
        again = server.client.post("/v1/jobs", files=files, data=data, headers=as_["alice"])
        assert again.status_code == 200 and again.json()["id"] == alice.json()["id"]  # her own duplicate
        bob = server.client.post("/v1/jobs", files=files, data=data, headers=as_["bob"])
        assert bob.status_code == 202 and bob.json()["id"] != alice.json()["id"], bob.text
        first = alice.json()["id"]
        for method, suffix in (("GET", ""), ("GET", "/report"), ("GET", "/artifacts"), ("DELETE", "")):
            response = server.client.request(method, f"/v1/jobs/{first}{suffix}", headers=as_["bob"])
            assert response.status_code == 404 and first in response.json()["detail"], (method, suffix, response.text)
        listed = server.client.get("/v1/jobs", headers=as_["bob"]).json()
        assert listed["total"] == 1 and [j["id"] for j in listed["jobs"]] == [bob.json()["id"]]
        everyone = server.client.get("/v1/jobs", headers=as_["admin"]).json()
        assert everyone["total"] == 2
        assert server.client.get(f"/v1/jobs/{first}", headers=as_["admin"]).status_code == 200
        assert server.stored(first).tenant == "alice" and server.stored(bob.json()["id"]).tenant == "bob"
        assert server.client.delete(f"/v1/jobs/{first}", headers=as_["alice"]).json()["state"] == "cancelled"
    finally:
        server.stop()
