"""A small client of the bcf HTTP API, and `run_remote`: `bcf batch --submit` with the service doing the work.

Materials are submitted at once (the service queues them and its workers decide the parallelism), then polled;
each finished job's artifact zip is downloaded, checked (`load_export` verifies every file against the
manifest) and put in place atomically, like a local `bcf compress` folder.
"""

from __future__ import annotations

import json
import shutil
import time
import zipfile
from pathlib import Path
from typing import Any, Optional, Sequence

import httpx

from bcf.core import (ExportError, JobOptions, OutputExistsError, TrainingProgress, load_export, replace_folder,
                      staging_folder)
from bcf.jobs.batch import BatchItem, BatchMaterial, EventCallback, MaterialEvent, check_replaceable
from bcf.jobs.records import FINAL_STATES, JobView

__all__ = ["JobRejected", "ServiceClient", "ServiceUnavailable", "run_remote"]


class ServiceUnavailable(RuntimeError):
    """The service cannot be reached or refuses us as a whole (wrong URL, token, server error)."""


class JobRejected(ValueError):
    """The service refused one material (its 4xx detail says why)."""


class ServiceClient:
    def __init__(self, url: str, token: Optional[str] = None, timeout: float = 300.0):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.url = url.rstrip("/")
        self.http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout)

    def close(self) -> None:
        self.http.close()

    def _request(self, method: str, path: str, refused: type[Exception] = ServiceUnavailable,
                 **kwargs: Any) -> httpx.Response:
        """A 2xx response. ServiceUnavailable when the service cannot be used at all (unreachable, wrong token,
        server error); `refused` when it answers this one request with a 4xx."""
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            raise ServiceUnavailable(f"{self.url}: {exc}") from None
        if response.status_code == 401:
            raise ServiceUnavailable(f"{self.url}: {_detail(response)} (pass --token)")
        if response.status_code >= 500:
            raise ServiceUnavailable(f"{self.url}: HTTP {response.status_code}: {_detail(response)}")
        if not response.is_success:
            raise refused(f"{method} {path}: the service refused it (HTTP {response.status_code}): "
                          f"{_detail(response)}")
        return response

    def check(self) -> None:
        """Fail early on a wrong URL or token, before anything is uploaded."""
        self._request("GET", "/v1/jobs", params={"limit": 1})

    def submit(self, entry: BatchMaterial, options: JobOptions) -> JobView:
        files = {role: (Path(path).name, Path(path).read_bytes()) for role, path in entry.files.roles().items()}
        payload = options.model_dump(mode="json", exclude={"device"}, exclude_none=True)
        if entry.files.normal_convention and "normal_convention" not in payload:
            payload["normal_convention"] = entry.files.normal_convention
        response = self._request("POST", "/v1/jobs", JobRejected, files=files, data={"options": json.dumps(payload)})
        return JobView.model_validate(response.json())

    def job(self, job_id: str) -> JobView:
        return JobView.model_validate(self._request("GET", f"/v1/jobs/{job_id}").json())

    def download_artifacts(self, job_id: str, target: Path) -> None:
        try:
            with self.http.stream("GET", f"/v1/jobs/{job_id}/artifacts") as response:
                if response.status_code != 200:
                    response.read()
                    raise ServiceUnavailable(f"{self.url}: artifacts of job {job_id}: HTTP "
                                             f"{response.status_code}: {_detail(response)}")
                with target.open("wb") as out:
                    for chunk in response.iter_bytes():
                        out.write(chunk)
        except httpx.HTTPError as exc:
            raise ServiceUnavailable(f"{self.url}: {exc}") from None


def _detail(response: httpx.Response) -> str:
    try:
        return str(response.json().get("detail", response.text))
    except ValueError:
        return response.text.strip()[:300]


def _install(client: ServiceClient, job_id: str, output: Path) -> None:
    """Download the job's artifacts, check them, and replace `output` with them atomically."""
    staged = staging_folder(output)
    try:
        archive = staged.with_suffix(".zip")
        client.download_artifacts(job_id, archive)
        with zipfile.ZipFile(archive) as z:
            z.extractall(staged)
        archive.unlink()
        load_export(staged)  # every file against the manifest's SHA-256
        replace_folder(staged, output)
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        staged.with_suffix(".zip").unlink(missing_ok=True)
        raise


def _progress(job: JobView) -> Optional[TrainingProgress]:
    p = job.progress
    if job.state != "running" or p.phase is None:
        return None
    return TrainingProgress(phase=p.phase, iteration=p.iteration, total=p.total, psnr=p.psnr or 0.0,
                            iterations_per_s=0.0, eta_s=p.eta_s or 0.0, elapsed_s=0.0)


def run_remote(todo: Sequence[BatchMaterial], options: JobOptions, client: ServiceClient,
               events: Optional[EventCallback] = None, poll_s: float = 1.0) -> list[BatchItem]:
    """Submit every material, then follow the jobs and install each result as it finishes. Items come back
    in the order of `todo`. Raises ServiceUnavailable when the service as a whole cannot be used."""
    emit = events or (lambda event: None)
    client.check()
    items: dict[int, BatchItem] = {}
    running: dict[int, tuple[str, float]] = {}  # index -> (job id, submitted at)
    for index, entry in enumerate(todo):
        name = entry.found.material
        try:
            if entry.found.problems:
                raise JobRejected("; ".join(entry.found.problems))
            check_replaceable(entry.output)
            job = client.submit(entry, options)
        except (JobRejected, OutputExistsError, OSError) as exc:
            items[index] = entry.item("failed", error=str(exc))
            emit(MaterialEvent(name, "finished", item=items[index]))
            continue
        running[index] = (job.id, time.perf_counter())
        emit(MaterialEvent(name, "started"))
    while running:
        for index, (job_id, submitted) in list(running.items()):
            entry = todo[index]
            job = client.job(job_id)
            if job.state not in FINAL_STATES:
                progress = _progress(job)
                if progress is not None:
                    emit(MaterialEvent(entry.found.material, "progress", progress))
                continue
            seconds = round(time.perf_counter() - submitted, 2)
            if job.state == "succeeded" and job.result is not None:
                try:
                    _install(client, job_id, entry.output)
                    item = entry.item("compressed", psnr=job.result.psnr, ssim=job.result.ssim,
                                      size_bytes=job.result.size_bytes, seconds=seconds, job_id=job_id)
                except (ExportError, zipfile.BadZipFile, OSError) as exc:
                    item = entry.item("failed", error=f"result of job {job_id} unusable: {exc}", seconds=seconds,
                                      job_id=job_id)
            else:
                item = entry.item("failed", error=f"job {job_id} {job.state}: {job.error or 'no message'}",
                                  seconds=seconds, job_id=job_id)
            items[index] = item
            del running[index]
            emit(MaterialEvent(entry.found.material, "finished", item=item))
        if running:
            time.sleep(poll_s)
    return [items[i] for i in range(len(todo))]
