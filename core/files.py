"""Writing files and folders so that nothing is ever half-written, and hashing their contents.

A file is written beside its destination under a hidden temporary name and moved over it at the end; a
folder is built in a hidden staging sibling (`staging_folder`) and swapped in whole (`replace_folder`).
A crash or Ctrl-C leaves the destination as it was, plus at most a staging folder that `staging_leftovers` finds.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_path", "file_sha256", "replace_folder", "staging_folder", "staging_leftovers", "write_text_atomic"]

_STAGING = ".partial-"


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; move it onto `path` only if the block succeeds. The temporary
    name keeps the suffix, because OpenImageIO picks an image format by extension."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def write_text_atomic(path: Path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` through `atomic_path`; returns `path`."""
    with atomic_path(Path(path)) as temporary:
        temporary.write_text(text, encoding="utf-8")
    return Path(path)


def staging_folder(output: Path) -> Path:
    """A new hidden folder beside `output` in which to build it (then `replace_folder`)."""
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{output.name}{_STAGING}", dir=output.parent))


def staging_leftovers(output: Path) -> list[Path]:
    """Staging folders of `output` that a killed process left behind."""
    output = Path(output)
    return sorted(output.parent.glob(f".{output.name}{_STAGING}*"))


def replace_folder(staged: Path, output: Path) -> None:
    """Move the finished `staged` folder to `output`, replacing it; `output` is never half-written."""
    if output.exists():
        old = output.with_name(f".{output.name}.old-{os.getpid()}")
        output.rename(old)
        staged.rename(output)
        shutil.rmtree(old, ignore_errors=True)
    else:
        staged.rename(output)


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes (manifests record it per input; batches compare it to skip unchanged inputs)."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as stream:
        for chunk in iter(lambda: stream.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()
