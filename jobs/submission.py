"""Job creation: a material's files, already on disk, -> a validated job with its inputs stored, in the queue.

The submitter (the HTTP service) stages the files, keeps its protocol's concerns to itself and words the
`bcf.core.InputError`s raised here for its users. Inputs are stored as `<role>/<file name>`, so messages that
name files (`the files differ in size: a.png 64x64, ...`) name them as the submitter's client knows them.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import uuid
from pathlib import Path
from typing import Optional

from pydantic import BaseModel, ConfigDict

from bcf.core import (InputError, InspectedMaterial, JobOptions, MaterialFiles, Role, TextureSet, check_memory,
                      decode_texture_set, inspect_texture_set, resolve_material, resolve_options, result_identity)
from bcf.jobs.settings import Settings
from bcf.jobs.storage import ObjectStoreUnavailable
from bcf.jobs.queue import JobQueue
from bcf.jobs.records import DEFAULT_TENANT, InputFile, Job

__all__ = ["StagedMaterial", "load_job_material", "submit_material"]


class StagedMaterial(BaseModel):
    """One material's files on disk, per role or in a folder where their names give the roles (as for
    `bcf compress FOLDER`). Submitting moves the files used into the job's inputs."""

    model_config = ConfigDict(extra="forbid")

    files: dict[Role, Path] = {}
    folder: Optional[Path] = None
    name: Optional[str] = None  # the job's name; None: the albedo file's stem
    client_names: dict[Role, str] = {}  # the names the client gave the files of `files`, shown back only


def _new_job(material: StagedMaterial, files: dict[Role, Path], inspected: InspectedMaterial, options: JobOptions,
             tenant: str, callback_url: Optional[str]) -> Job:
    """The job's record. Its input key hashes the tenant and what decides the result (`bcf.core.result_identity`:
    the inputs' bytes by role, the normal convention and size they were loaded with, the resolved options
    without the device) and the baselines, not the names: the same files under other names are the same job,
    within one tenant (another's resubmission is a job of its own, and learns nothing of the first)."""
    source = inspected.source
    hashes = {f.role: f.sha256 for f in source.files}
    resolved = options.model_copy(update={"normal_convention": source.normal_convention})
    identity = result_identity(hashes, source.normal_convention, (source.width, source.height),
                               resolved.compress_options())
    key = json.dumps({"result": identity.key(), "baselines": sorted(resolved.baselines), "tenant": tenant},
                     sort_keys=True)
    inputs = [InputFile(role=role, name=material.client_names.get(role, path.name), stored_as=f"{role}/{path.name}",
                        sha256=hashes[role], bytes=path.stat().st_size) for role, path in files.items()]
    return Job(id=uuid.uuid4().hex[:16], name=source.name, options=resolved, inputs=inputs,
               input_key=hashlib.sha256(key.encode()).hexdigest(), notes=list(inspected.notes), tenant=tenant,
               callback_url=callback_url)


def submit_material(queue: JobQueue, material: StagedMaterial, options: JobOptions,
                    tenant: str = DEFAULT_TENANT, callback_url: Optional[str] = None) -> tuple[Job, bool]:
    """Validate the material from its files' headers (roles, formats, sizes, the pixel limit, the memory estimate;
    no pixel is decoded here: the worker decodes, and a corrupt file fails the job), store its inputs, queue the
    job: (job, created). Resubmitting a queued, running or succeeded job's inputs and options returns that job. Raises `bcf.core.InputError` for whatever the client must fix."""
    if "device" in options.model_fields_set:  # any worker may take the job: the device is the worker's
        raise InputError("{} is chosen by the worker that runs the job ('bcf worker --device')",
                         fix="remove it from the options", options=["device"])
    resolved = resolve_material(material.folder, MaterialFiles(**material.files,
                                                               normal_convention=options.normal_convention))
    files = resolved.roles()
    inspected = inspect_texture_set(resolved, name=material.name, max_pixels=queue.settings.max_texture_pixels)
    _check_memory(inspected, options, queue.settings)
    job = _new_job(material, files, inspected, options, tenant, callback_url)
    folder = queue.inputs_path(job.id)
    try:  # inputs in place before the job is queued: a worker may start it at once
        for stored in job.inputs:
            (folder / stored.role).mkdir(parents=True)
            files[stored.role].rename(folder / stored.stored_as)  # staging shares the data directory's disk
        queue.storage.put_inputs(job.id, folder)  # object storage: where the workers fetch them from
        stored_job, created = queue.submit(job)
    except BaseException:
        _discard_inputs(queue, job.id)
        raise
    if not created:
        _discard_inputs(queue, job.id)  # the existing job has its own copy
    elif queue.storage.remote:
        queue.remove_local_inputs(job.id)  # the local copy was staging: workers read the stored one
    return stored_job, created


def _discard_inputs(queue: JobQueue, job_id: str) -> None:
    """The inputs stored for a job that was not created (a duplicate, or a failed submission)."""
    shutil.rmtree(queue.inputs_path(job_id), ignore_errors=True)
    if queue.storage.remote:
        try:
            queue.storage.remove_inputs(job_id)
        except ObjectStoreUnavailable:
            pass  # unreferenced objects: nothing reads them


def _check_memory(inspected: InspectedMaterial, options: JobOptions, settings: Settings) -> None:
    """`bcf.core.MemoryBudgetError` when the job's estimated peak memory is over the budget of `settings`."""
    check_memory(inspected.source.width, inspected.source.height, resolve_options(options.compress_options()),
                 settings.memory_budget(), "BCF_JOB_MEMORY_MB")


def load_job_material(job: Job, inputs: Path, settings: Settings) -> TextureSet:
    """The job's texture set from its stored inputs (`inputs` is the job's folder, `queue.inputs_path`): their
    pixels decoded here, in the worker, for the first time, after the limits of this worker's `settings` are
    checked again from the headers. Raises `bcf.core.InputError` (the job fails with it) for a file over a
    limit, one that does not decode, or one that is no longer the one submitted."""
    files = MaterialFiles(**{f.role: inputs / f.stored_as for f in job.inputs},
                          normal_convention=job.options.normal_convention)
    inspected = inspect_texture_set(files, name=job.name, max_pixels=settings.max_texture_pixels)
    _check_memory(inspected, job.options, settings)  # this worker's budget: farm workers may differ
    submitted = {f.role: f.sha256 for f in job.inputs}
    for stored in inspected.source.files:
        if stored.sha256 != submitted[stored.role]:
            raise InputError("the stored input differs from the file submitted (SHA-256 mismatch)",
                             file=inspected.paths[stored.role], role=stored.role, fix="submit the material again")
    return decode_texture_set(inspected)
