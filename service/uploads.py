"""POST /v1/jobs, the HTTP side: the multipart form, its files staged on disk (making the job is
`bcf.jobs.submission`'s), and `bcf.core.InputError`s worded for HTTP clients.

Files are staged in a private folder under BCF_DATA_DIR/uploads, removed afterwards: a rejected request leaves
nothing behind. Role files are staged as `<role>/<name>`, zip images by base name, names made safe
([A-Za-z0-9._-], not hidden, short) but otherwise the client's, so messages name files as the client did.
"""

from __future__ import annotations

import errno
import re
import stat
import tempfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from typing import BinaryIO, Optional, Sequence

from fastapi import File, Form, HTTPException, Request, UploadFile
from pydantic import Json

from bcf.core import IMAGE_EXTENSIONS, ROLES, InputError, JobOptions
from bcf.jobs.callbacks import CallbackError, checked_callback_url
from bcf.jobs.queue import JobQueue
from bcf.jobs.records import Job
from bcf.jobs.settings import Settings
from bcf.jobs.store import StoreFull
from bcf.jobs.submission import StagedMaterial, submit_material

__all__ = ["DiskFull", "Upload", "client_message", "read_upload", "submit_upload"]

FORM_FIELDS = (*ROLES, "material", "options", "callback_url")
ACCEPTED_FORMATS = "PNG, JPEG, EXR, TIFF or TGA"
# Leading bytes of each accepted format but TGA (which has none), and the file extensions that format goes by.
_SIGNATURES = ((b"\x89PNG\r\n\x1a\n", (".png",)), (b"\xff\xd8\xff", (".jpg", ".jpeg")),
               (b"\x76\x2f\x31\x01", (".exr",)), (b"II*\x00", (".tif", ".tiff")), (b"MM\x00*", (".tif", ".tiff")))
_COPY_CHUNK = 1 << 20
# The files by form field (a role, or "material"), the options, the callback URL.
Upload = tuple[dict[str, UploadFile], JobOptions, Optional[str]]
_DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


class DiskFull(Exception):
    """The data directory's disk filled while an upload was stored (the app answers 507)."""


async def read_upload(request: Request,
                      albedo: Optional[UploadFile] = File(None, description="base colour, sRGB"),
                      normal: Optional[UploadFile] = File(None, description="tangent-space normal map"),
                      arm: Optional[UploadFile] = File(None, description="packed AO / roughness / metalness"),
                      ao: Optional[UploadFile] = File(None), roughness: Optional[UploadFile] = File(None),
                      metalness: Optional[UploadFile] = File(None),
                      material: Optional[UploadFile] = File(None, description="zip of a material folder, "
                                                                              "instead of the files per role"),
                      options: Optional[Json[JobOptions]] = Form(None, description='e.g. {"preset": "fast"}'),
                      callback_url: Optional[str] = Form(
                          None, description="http(s) URL POSTed the job object when the job ends, signed with "
                                            "BCF_CALLBACK_SECRET (X-Bcf-Signature: sha256=<hex HMAC>)")
                      ) -> Upload:
    """The form of POST /v1/jobs (a FastAPI dependency, so OpenAPI lists the fields and FastAPI checks the
    options): files per role or a zip, and the options; 400 for fields it does not know or that appear twice."""
    form = await request.form()
    unknown = sorted(set(form.keys()) - set(FORM_FIELDS))
    if unknown:
        raise HTTPException(400, f"unknown form field(s) {', '.join(unknown)}; expected {', '.join(FORM_FIELDS)}")
    if any(len(form.getlist(name)) > 1 for name in FORM_FIELDS):
        raise HTTPException(400, "each form field may appear once")
    given = {"albedo": albedo, "normal": normal, "arm": arm, "ao": ao, "roughness": roughness,
             "metalness": metalness, "material": material}
    try:
        url = checked_callback_url(callback_url)
    except CallbackError as exc:
        raise HTTPException(422, str(exc)) from None
    return {name: f for name, f in given.items() if f is not None}, options or JobOptions(), url


# ---------------------------------------------------------------------------------------------- role files


def _safe_name(text: Optional[str], fallback: str) -> str:
    """A display / file name made only of [A-Za-z0-9._-], never hidden, at most 80 characters."""
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "_", text or "").strip("._")[:80]
    return cleaned or fallback


def _copy_limited(source: BinaryIO, target: Path, limit: int, what: str) -> int:
    """Copy at most `limit` bytes; HTTPException(413) past it (zip headers may understate entry sizes)."""
    written = 0
    with target.open("wb") as out:
        while chunk := source.read(_COPY_CHUNK):
            written += len(chunk)
            if written > limit:
                raise HTTPException(413, f"{what}: larger than the limit of {limit / 2**20:.0f} MiB")
            out.write(chunk)
    return written


def _stage_role_file(role: str, upload: UploadFile, staging: Path, limit: int) -> Path:
    """`staging/<role>/<the client's base name, made safe, with an extension of its format>`."""
    head = upload.file.read(32)
    upload.file.seek(0)
    extensions = next((found for signature, found in _SIGNATURES if head.startswith(signature)), ())
    if not extensions and (upload.filename or "").lower().endswith(".tga") and len(head) >= 18:
        extensions = (".tga",)  # TGA has no signature: its name must say so
    shown = f"{role} ({upload.filename or 'no file name'})"
    if not extensions:
        raise HTTPException(415, f"{shown}: not a {ACCEPTED_FORMATS} image")
    name = PurePosixPath((upload.filename or "").replace("\\", "/"))
    extension = name.suffix if name.suffix.lower() in extensions else extensions[0]
    target = staging / role / (_safe_name(name.stem, role) + extension)
    target.parent.mkdir()
    _copy_limited(upload.file, target, limit, shown)
    return target


# ---------------------------------------------------------------------------------------------------- zip


def _entry_name(info: zipfile.ZipInfo) -> Optional[PurePosixPath]:
    """The entry's path, or None for directories and OS clutter; HTTPException for anything unsafe."""
    raw = info.filename.replace("\\", "/")
    path = PurePosixPath(raw)
    if raw.startswith("/") or re.match(r"^[A-Za-z]:", raw) or ".." in path.parts:
        raise HTTPException(400, f"material zip: entry {info.filename!r} points outside the archive "
                                 "(absolute path or '..'); zip the material folder itself")
    if stat.S_ISLNK(info.external_attr >> 16):
        raise HTTPException(400, f"material zip: entry {info.filename!r} is a symbolic link; only plain files "
                                 "are accepted")
    if info.flag_bits & 0x1:
        raise HTTPException(400, f"material zip: entry {info.filename!r} is encrypted")
    if info.is_dir() or "__MACOSX" in path.parts or path.name.startswith("."):
        return None
    return path


def _unpack_zip(upload: UploadFile, folder: Path, max_entries: int, max_total: int) -> str:
    """Extract the image entries of a material zip into `folder` by sanitised base name; returns the material
    name (the zip's single top folder, else the zip's file stem)."""
    try:
        archive = zipfile.ZipFile(upload.file)
    except (zipfile.BadZipFile, OSError):
        raise HTTPException(415, f"material ({upload.filename or 'no file name'}): not a zip archive") from None
    with archive:
        entries = archive.infolist()
        if len(entries) > max_entries:
            raise HTTPException(400, f"material zip: {len(entries)} entries, more than the limit of {max_entries}")
        declared = sum(info.file_size for info in entries)
        if declared > max_total:
            raise HTTPException(413, f"material zip: {declared / 2**20:.0f} MiB uncompressed, more than the limit "
                                     f"of {max_total / 2**20:.0f} MiB")
        paths = [(info, _entry_name(info)) for info in entries]
        files = [(info, path) for info, path in paths if path is not None]
        images = [(info, path) for info, path in files if path.suffix.lower() in IMAGE_EXTENSIONS]
        if not images:
            raise HTTPException(422, f"material zip: no image files ({ACCEPTED_FORMATS}) found")
        left = max_total
        taken: dict[str, str] = {}
        for info, path in images:
            name = _safe_name(path.name, "image")
            if name.lower() in taken:
                raise HTTPException(400, f"material zip: {taken[name.lower()]!r} and {info.filename!r} have the same "
                                         "file name; a material zip holds one texture set")
            taken[name.lower()] = info.filename
            try:
                with archive.open(info) as stream:
                    left -= _copy_limited(stream, folder / name, left, "material zip (uncompressed)")
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
                raise HTTPException(415, f"material zip: entry {info.filename!r} cannot be extracted: {exc}") from None
        tops = {path.parts[0] for _, path in files if len(path.parts) > 1}
        top_level_files = any(len(path.parts) == 1 for _, path in files)
        stem = tops.pop() if len(tops) == 1 and not top_level_files else PurePosixPath(upload.filename or "").stem
        return _safe_name(stem, "material")


# ------------------------------------------------------------------------------------------------- submit


def _stage(files: dict[str, UploadFile], staging: Path, settings: Settings) -> StagedMaterial:
    """The sent files in `staging`, within the limits: a zip unpacked (its roles are found later), or files per role."""
    if "material" in files and len(files) > 1:
        raise HTTPException(400, "send either a material zip or texture files per role, not both")
    if "material" in files:
        folder = staging / "zip"
        folder.mkdir()
        name = _unpack_zip(files["material"], folder, settings.max_zip_entries, int(settings.max_unzipped_mb * 2**20))
        return StagedMaterial(folder=folder, name=name)
    if not files:
        raise HTTPException(422, "no material: send the texture files as fields albedo, normal and arm (or ao, "
                                 "roughness, metalness), or a zip of the material folder as field material")
    limit = int(settings.max_upload_mb * 2**20)
    return StagedMaterial(files={role: _stage_role_file(role, f, staging, limit) for role, f in files.items()},
                          client_names={role: f.filename or "(no file name)" for role, f in files.items()})


def _option_wording(names: Sequence[str]) -> str:
    """Option names as a request spells them: roles are form fields, the rest keys of the options JSON."""
    if all(name in ROLES for name in names):
        return f"the form field{'s' if len(names) > 1 else ''} {', '.join(names)}"
    return " or ".join(f'options {{"{name}": ...}}' for name in names)


def client_message(exc: InputError, staged: StagedMaterial) -> str:
    """`exc` for the client: a role file as `role (name it was sent as)`, the material as a whole by how it
    came (never a server path), other files by their names, options as request fields."""
    shown = {path: f"{role} ({staged.client_names[role]})" for role, path in staged.files.items()}
    whole = {staged.folder, *(path.parent for path in staged.files.values())}
    what = "material zip" if staged.folder else "material"
    return exc.message(options=_option_wording,
                       file=lambda path: shown.get(Path(path)) or (what if Path(path) in whole else Path(path).name))


def submit_upload(queue: JobQueue, upload: Upload, tenant: str) -> tuple[Job, bool]:
    """Stage the upload, then submit it (`bcf.jobs.submission.submit_material`): (job, created). HTTPException for
    anything the client must fix, DiskFull when the disk fills meanwhile; the staging folder is removed either
    way (the job's inputs moved out)."""
    try:
        return _staged_and_submitted(queue, upload, tenant)
    except StoreFull as exc:
        raise DiskFull(f"the job store's disk is full: {exc}") from None
    except OSError as exc:
        if exc.errno not in _DISK_FULL:
            raise
        raise DiskFull("the data directory's disk is full: it filled while the upload was stored (nothing was "
                       "kept); free space, and keep some free with BCF_MIN_FREE_DISK_MB") from None


def _staged_and_submitted(queue: JobQueue, upload: Upload, tenant: str) -> tuple[Job, bool]:
    uploads = queue.settings.uploads_dir
    uploads.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="upload-", dir=uploads, ignore_cleanup_errors=True) as staging:
        files, options, callback_url = upload
        staged = _stage(files, Path(staging), queue.settings)
        try:
            return submit_material(queue, staged, options, tenant, callback_url)
        except InputError as exc:
            raise HTTPException(422, client_message(exc, staged)) from None
