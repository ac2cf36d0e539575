"""Turning an upload (one file per role, or a zip of a material folder) into a validated job.

Every check happens in a private staging folder under BCF_DATA_DIR/uploads that is deleted afterwards, so a
rejected request leaves nothing behind. Client file names never become paths: role files are stored as
<role>.<ext> with the extension of the format their bytes show, and zip entries are reduced to a sanitised
base name (only to let name-based role discovery work) inside the staging folder.
"""

from __future__ import annotations

import re
import shutil
import stat
import tempfile
import uuid
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO, Optional

from bcf.core import (IMAGE_EXTENSIONS, JobOptions, MaterialError, MaterialFiles, load_texture_set,
                      normal_convention_from_name, resolve_material, result_identity)
from bcf.jobs.queue import JobQueue
from bcf.jobs.records import InputFile, Job, input_key

__all__ = ["BadUpload", "ROLE_FIELDS", "UploadedFile", "submit_upload"]

ROLE_FIELDS: tuple[str, ...] = ("albedo", "normal", "arm", "ao", "roughness", "metalness")
ACCEPTED_FORMATS = "PNG, JPEG, EXR, TIFF or TGA"
_COPY_CHUNK = 1 << 20


class BadUpload(ValueError):
    """A request the client must fix; `status` is the HTTP status to answer with."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


@dataclass
class UploadedFile:
    field: str  # the form field: a role or "material"
    filename: Optional[str]  # as the client sent it, only shown back
    stream: BinaryIO


def _sniff(head: bytes, filename: Optional[str]) -> Optional[str]:
    """The image format's extension from the first bytes; TGA has no signature, so its name must say .tga."""
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return ".png"
    if head.startswith(b"\xff\xd8\xff"):
        return ".jpg"
    if head.startswith(b"\x76\x2f\x31\x01"):
        return ".exr"
    if head.startswith((b"II*\x00", b"MM\x00*")):
        return ".tif"
    if filename and filename.lower().endswith(".tga") and len(head) >= 18:
        return ".tga"
    return None


def _safe_name(text: Optional[str], fallback: str) -> str:
    """A display / file name made only of [A-Za-z0-9._-], never hidden, at most 80 characters."""
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "_", text or "").strip("._")[:80]
    return cleaned or fallback


def _copy_limited(source: BinaryIO, target: Path, limit: int, what: str) -> int:
    """Copy at most `limit` bytes; BadUpload(413) past it (zip headers may understate entry sizes)."""
    written = 0
    with target.open("wb") as out:
        while chunk := source.read(_COPY_CHUNK):
            written += len(chunk)
            if written > limit:
                raise BadUpload(413, f"{what}: larger than the limit of {limit / 2**20:.0f} MiB")
            out.write(chunk)
    return written


def _store_role_file(upload: UploadedFile, folder: Path, limit: int) -> tuple[Path, str]:
    head = upload.stream.read(32)
    upload.stream.seek(0)
    extension = _sniff(head, upload.filename)
    shown = upload.filename or "(no file name)"
    if extension is None:
        raise BadUpload(415, f"{upload.field} ({shown}): not a {ACCEPTED_FORMATS} image")
    target = folder / f"{upload.field}{extension}"
    _copy_limited(upload.stream, target, limit, f"{upload.field} ({shown})")
    return target, shown


# ---------------------------------------------------------------------------------------------------- zip


def _entry_name(info: zipfile.ZipInfo) -> Optional[PurePosixPath]:
    """The entry's path, or None for directories and OS clutter; BadUpload for anything unsafe."""
    raw = info.filename.replace("\\", "/")
    path = PurePosixPath(raw)
    if raw.startswith("/") or re.match(r"^[A-Za-z]:", raw) or ".." in path.parts:
        raise BadUpload(400, f"material zip: entry {info.filename!r} points outside the archive "
                             "(absolute path or '..'); zip the material folder itself")
    if stat.S_ISLNK(info.external_attr >> 16):
        raise BadUpload(400, f"material zip: entry {info.filename!r} is a symbolic link; only plain files "
                             "are accepted")
    if info.flag_bits & 0x1:
        raise BadUpload(400, f"material zip: entry {info.filename!r} is encrypted")
    if info.is_dir() or "__MACOSX" in path.parts or path.name.startswith("."):
        return None
    return path


def _unpack_zip(upload: UploadedFile, folder: Path, max_entries: int, max_total: int) -> str:
    """Extract the image entries of a material zip into `folder` by sanitised base name; returns the material
    name (the zip's single top folder, else the zip's file stem)."""
    try:
        archive = zipfile.ZipFile(upload.stream)
    except (zipfile.BadZipFile, OSError):
        raise BadUpload(415, f"material ({upload.filename or 'no file name'}): not a zip archive") from None
    with archive:
        entries = archive.infolist()
        if len(entries) > max_entries:
            raise BadUpload(400, f"material zip: {len(entries)} entries, more than the limit of {max_entries}")
        declared = sum(info.file_size for info in entries)
        if declared > max_total:
            raise BadUpload(413, f"material zip: {declared / 2**20:.0f} MiB uncompressed, more than the limit "
                                 f"of {max_total / 2**20:.0f} MiB")
        paths = [(info, _entry_name(info)) for info in entries]
        files = [(info, path) for info, path in paths if path is not None]
        images = [(info, path) for info, path in files if path.suffix.lower() in IMAGE_EXTENSIONS]
        if not images:
            raise BadUpload(422, f"material zip: no image files ({ACCEPTED_FORMATS}) found")
        left = max_total
        taken: dict[str, str] = {}
        for info, path in images:
            name = _safe_name(path.name, "image")
            if name.lower() in taken:
                raise BadUpload(400, f"material zip: {taken[name.lower()]!r} and {info.filename!r} have the same "
                                     "file name; a material zip holds one texture set")
            taken[name.lower()] = info.filename
            try:
                with archive.open(info) as stream:
                    left -= _copy_limited(stream, folder / name, left, "material zip (uncompressed)")
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
                raise BadUpload(415, f"material zip: entry {info.filename!r} cannot be extracted: {exc}") from None
        tops = {path.parts[0] for _, path in files if len(path.parts) > 1}
        top_level_files = any(len(path.parts) == 1 for _, path in files)
        stem = tops.pop() if len(tops) == 1 and not top_level_files else PurePosixPath(upload.filename or "").stem
        return _safe_name(stem, "material")


# ------------------------------------------------------------------------------------------------- submit


def _client_message(message: str, names: dict[str, str]) -> str:
    """A MaterialError's text with staging paths replaced by what the client sent, and CLI options by fields."""
    for path, shown in sorted(names.items(), key=lambda item: -len(item[0])):
        message = message.replace(path, shown).replace(f" {Path(path).name} ", f" {shown} ")
    for option, field in (("--normal-convention", 'options {"normal_convention": ...}'),
                          ("--albedo/--normal/--arm/--roughness", "the form fields albedo, normal, arm, roughness"),
                          ("--arm", "arm"), ("--ao", "ao"), ("--roughness", "roughness"),
                          ("--metalness", "metalness")):
        message = message.replace(option, field)
    return message


def submit_upload(queue: JobQueue, uploads: list[UploadedFile], options: JobOptions) -> tuple[Job, bool]:
    """Validate an upload completely (files, zip, loading the material), then store its inputs and submit the
    job. Returns (job, created); an unchanged resubmission returns the existing job. Raises BadUpload."""
    settings = queue.settings
    by_field = {u.field: u for u in uploads}
    if "material" in by_field and len(by_field) > 1:
        raise BadUpload(400, "send either a material zip or texture files per role, not both")
    if not by_field:
        raise BadUpload(422, "no material: send the texture files as fields albedo, normal and arm (or ao, "
                             "roughness, metalness), or a zip of the material folder as field material")
    limit = int(settings.max_upload_mb * 2**20)
    settings.uploads_dir.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix="upload-", dir=settings.uploads_dir))
    try:
        stored = staging / "inputs"
        stored.mkdir()
        names: dict[str, str] = {str(staging / "zip"): "material zip", str(stored): "upload"}
        if "material" in by_field:
            unpacked = staging / "zip"
            unpacked.mkdir()
            name = _unpack_zip(by_field["material"], unpacked, settings.max_zip_entries,
                               int(settings.max_unzipped_mb * 2**20))
            try:
                found = resolve_material(unpacked, MaterialFiles(
                    normal_convention=options.normal_convention))
            except MaterialError as exc:
                raise BadUpload(422, _client_message(str(exc), names)) from None
            originals: dict[str, str] = {}
            files: dict[str, Path] = {}
            for role, path in found.roles().items():
                target = stored / f"{role}{Path(path).suffix.lower()}"
                Path(path).rename(target)  # the staging folder is one file system: no second copy
                originals[role], files[role] = Path(path).name, target
                names[str(target)] = f"{role} ({Path(path).name})"
            convention = found.normal_convention
        else:
            originals, files = {}, {}
            for field, upload in by_field.items():
                target, shown = _store_role_file(upload, stored, limit)
                originals[field], files[field] = shown, target
                names[str(target)] = f"{field} ({shown})"
            albedo_name = by_field["albedo"].filename if "albedo" in by_field else None
            name = _safe_name(Path(albedo_name).stem if albedo_name else None, "material")
            convention = options.normal_convention or (normal_convention_from_name(
                by_field["normal"].filename or "") if "normal" in by_field else None)
        try:
            texture_set = load_texture_set(MaterialFiles(**files, normal_convention=convention),
                                                    name=name)
        except MaterialError as exc:
            raise BadUpload(422, _client_message(str(exc), names)) from None
        source = texture_set.source
        hashes = {f.role: f.sha256 for f in source.files}
        resolved_options = options.model_copy(update={"normal_convention": source.normal_convention})
        job = Job(id=uuid.uuid4().hex[:16], name=name, options=resolved_options,
                  inputs=[InputFile(role=role, name=originals[role], stored_as=path.name, sha256=hashes[role],
                                    bytes=path.stat().st_size) for role, path in files.items()],
                  input_key=input_key(result_identity(hashes, source.normal_convention, (source.width, source.height),
                                                      resolved_options.compress_options()), resolved_options.baselines),
                  notes=[_client_message(note, names) for note in texture_set.notes])
        # Inputs are in place before the job is queued: a worker may start it at once.
        final = queue.inputs_path(job.id)
        final.parent.mkdir(parents=True, exist_ok=True)
        stored.rename(final)
        try:
            result, created = queue.submit(job)
        except BaseException:
            shutil.rmtree(final, ignore_errors=True)
            raise
        if not created:
            shutil.rmtree(final, ignore_errors=True)  # the existing job has its own copy
        return result, created
    finally:
        shutil.rmtree(staging, ignore_errors=True)
