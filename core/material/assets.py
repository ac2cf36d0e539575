"""Asset-library scan: a folder tree -> the texture sets (materials) it holds, for `bcf batch`.

Each folder is looked at on its own, with the one-folder discovery of `bcf.core.material` (the same names, notes
and choices as `bcf compress FOLDER`). A folder usually holds one material; exporters such as Substance Painter
put several in one folder, told apart by the name before the map name (`Wood_BaseColor.png`,
`Metal_BaseColor.png`), so files are grouped by that prefix and each prefix that has an albedo is a material.

Nothing is decoded: only file names are read, plus the albedo's header for its size. A set that cannot be
compressed as found (a role missing or ambiguous) is still listed, with `problems`, so a batch can report it
and go on; image files that belong to no material are listed as `unplaced` with the reason.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Optional, Union

import pydantic

from bcf.core.material.naming import NOISE_TOKENS, choose_roles, classify_name, join_names, missing_roles, scan_files
from bcf.core.material.roles import (IMAGE_EXTENSIONS, ROLES, ExtraRole, MaterialError, MaterialFiles, NormalConvention,
                                     Role)
from bcf.core.material.texture_set import read_header

__all__ = ["AssetRole", "AssetScan", "FoundMaterial", "Unplaced", "scan_assets"]

AssetRole = Union[Role, ExtraRole]  # the maps bcf compresses and those a scan lists beside them

# Folders that hold no materials: archive and OS clutter (hidden names, starting with ".", are skipped too).
_SKIPPED_FOLDERS = frozenset({"__macosx", "__pycache__", "$recycle.bin", "system volume information"})
_TOKEN = re.compile(r"[^_\-.\s]+")  # the complement of _SEPARATORS: a name's tokens, with positions


class FoundMaterial(pydantic.BaseModel):
    """One texture set found in the tree; complete (no `problems`) means `bcf compress` can take it as is."""

    model_config = pydantic.ConfigDict(extra="forbid")

    material: str  # the folder name; "<folder name>/<prefix>" when one folder holds several materials
    dir: str  # the folder, relative to the scanned root, POSIX ("." for the root itself)
    output: str  # relative output folder: `dir`, or `dir/<prefix>` when the folder holds several materials
    files: dict[AssetRole, str]  # role -> path relative to the root (POSIX); opacity/height listed, not compressed
    normal_convention: Optional[NormalConvention]  # what the normal file's name says (None: unknown)
    resolution: Optional[tuple[int, int]]  # (width, height) of the albedo from its header; None: none/unreadable
    notes: list[str]  # discovery choices, to show the user
    problems: list[str]  # why it cannot be compressed as found; empty when complete

    def material_files(self, root: Path) -> MaterialFiles:
        """The compressible roles as absolute paths under `root`, with the normal convention, ready for
        `load_texture_set` (which checks completeness again)."""
        root = Path(root).resolve()
        roles = {role: root / path for role, path in self.files.items() if role in ROLES}
        return MaterialFiles(**roles, normal_convention=self.normal_convention)


class Unplaced(pydantic.BaseModel):
    """An image file that belongs to no material, so the user can rename or move it."""

    model_config = pydantic.ConfigDict(extra="forbid")

    path: str  # relative to the root, POSIX
    reason: str


class AssetScan(pydantic.BaseModel):
    """Everything `scan_assets` found under one root."""

    model_config = pydantic.ConfigDict(extra="forbid")

    materials: list[FoundMaterial]  # sorted by output
    unplaced: list[Unplaced]  # sorted by path


@dataclass(frozen=True)
class _Image:
    """One image file of a folder and what its name says."""

    path: Path
    rel: str  # relative to the root, POSIX
    role: Optional[AssetRole]  # None: no role (an unknown name, or an unused map that is not listed)
    unknown: bool  # the name matches no role and no known unused map
    key: str  # the prefix compared case-insensitively: lower-case tokens joined by "_"
    prefix: str  # the prefix as written in the file name


def scan_assets(root: Path) -> AssetScan:
    """The materials under `root` (recursively, in sorted order) and the images that fit none.

    Only image files (IMAGE_EXTENSIONS) count; hidden files and folders and archive clutter are
    skipped. Raises MaterialError if `root` is not a folder.
    """
    root = Path(root)
    if not root.is_dir():
        raise MaterialError(f"{'not a folder' if root.exists() else 'no such folder'}", file=root)
    materials: list[FoundMaterial] = []
    unplaced: list[Unplaced] = []
    for folder, images in _walk(root):
        found, left = _scan_folder(root, folder, images)
        materials.extend(found)
        unplaced.extend(left)
    materials.sort(key=lambda m: m.output)
    _flag_shared_outputs(materials)
    return AssetScan(materials=materials, unplaced=sorted(unplaced, key=lambda u: u.path))


# ------------------------------------------------------------------------------------------------ walking


def _walk(root: Path) -> Iterator[tuple[Path, list[_Image]]]:
    """(folder, its image files) for every folder with images, in sorted, deterministic order."""
    for current, folders, names in os.walk(root):
        folders[:] = sorted(f for f in folders if not _hidden(f) and f.lower() not in _SKIPPED_FOLDERS)
        folder = Path(current)
        paths = [folder / name for name in sorted(names)
                 if not _hidden(name) and Path(name).suffix.lower() in IMAGE_EXTENSIONS]
        paths = [path for path in paths if path.is_file()]
        if paths:
            yield folder, [_image(root, path) for path in paths]


def _hidden(name: str) -> bool:
    return name.startswith(".")  # also macOS `._name` resource forks, which look like images by extension


def _image(root: Path, path: Path) -> _Image:
    """Classify one image by its name (classify_name) and work out its prefix."""
    named = classify_name(path)
    role: Optional[AssetRole] = named.role if named.role is not None else named.extra
    spans = [(m.start(), m.end(), m.group().lower()) for m in _TOKEN.finditer(path.stem)][:named.prefix]
    # Resolution and format tokens before the map name (ambientCG's `Metal009_2K_Color`) are not part of the
    # material's name; numbers are (`denim_fabric_02`, `brick_01` next to `brick_02`).
    while spans and NOISE_TOKENS.fullmatch(spans[-1][2]) and not spans[-1][2].isdigit():
        spans.pop()
    return _Image(path=path, rel=path.relative_to(root).as_posix(), role=role,
                  unknown=named.role is None and not named.unused,
                  key="_".join(token for _, _, token in spans),
                  prefix=path.stem[spans[0][0]:spans[-1][1]] if spans else "")


# ---------------------------------------------------------------------------------------------- folders


def _scan_folder(root: Path, folder: Path, images: list[_Image]) -> tuple[list[FoundMaterial], list[Unplaced]]:
    """The materials of one folder and its images that fit none."""
    rel_dir = folder.relative_to(root).as_posix()
    name = folder.resolve().name if rel_dir == "." else folder.name
    unplaced = [Unplaced(path=image.rel, reason="name matches no role") for image in images if image.unknown]
    listed = [image for image in images if image.role is not None]
    albedo_keys = list(dict.fromkeys(image.key for image in listed if image.role == "albedo"))
    if len(albedo_keys) <= 1:
        # One material: the folder as `bcf compress FOLDER` sees it, every image included (so notes agree).
        if not any(image.role in ROLES for image in listed):
            unplaced += [Unplaced(path=image.rel, reason="no albedo, normal or roughness map in this folder")
                         for image in listed]
            return [], unplaced
        key = albedo_keys[0] if albedo_keys else None
        return [_material(root, folder, name, rel_dir, images, key)], unplaced
    found = []
    for key in albedo_keys:
        group = [image for image in listed if image.key == key]
        prefix = next(image.prefix for image in group if image.role == "albedo")
        # Files without a prefix (`albedo.png` next to `Wood_BaseColor.png`) are the folder's own material.
        label, output = (f"{name}/{prefix}", str(PurePosixPath(rel_dir) / prefix)) if prefix else (name, rel_dir)
        found.append(_material(root, folder, label, output, group, key))
    unplaced += [Unplaced(path=image.rel, reason=f"no albedo with the prefix '{image.prefix}' in this folder")
                 for image in listed if image.key not in albedo_keys]
    return found, unplaced


def _material(root: Path, folder: Path, name: str, output: str, images: list[_Image],
              key: str | None) -> FoundMaterial:
    """One material from `images` (all in `folder`) with the one-folder discovery; `key` is its albedo's prefix."""
    rel_dir = folder.relative_to(root).as_posix()
    problems: list[str] = []
    scan = scan_files(image.path for image in images)
    chosen = choose_roles(Path(rel_dir), scan, problems=problems)
    roles = chosen.roles()
    # A role with several candidates already has its problem; it is not missing as well.
    missing = missing_roles(role for role, candidates in scan.candidates.items() if candidates)
    if missing:
        problems.append(f"incomplete material: missing {', '.join(missing)}")
    files: dict[AssetRole, str] = {role: path.relative_to(root).as_posix() for role, path in roles.items()}
    notes = list(chosen.notes)
    for extra in ("height", "opacity"):
        path, note = _pick_extra(extra, [image for image in images if image.role == extra], key)
        if path is not None:
            files[extra] = path
        notes += note
    return FoundMaterial(material=name, dir=rel_dir, output=output, files=files,
                         normal_convention=chosen.normal_convention,
                         resolution=_resolution(roles["albedo"]) if "albedo" in roles else None,
                         notes=notes, problems=problems)


def _pick_extra(role: str, candidates: list[_Image], key: str | None) -> tuple[str | None, list[str]]:
    """The height (or opacity) file to list: the one with the material's prefix when there are several, else
    the first; a note names the others. Only listed, never compressed, so several are not a problem."""
    if not candidates:
        return None, []
    preferred = [image for image in candidates if image.key == key] or candidates
    chosen = preferred[0]
    others = [image.path.name for image in candidates if image is not chosen]
    note = [f"several {role} maps: listing {chosen.path.name}, not {join_names(others)}"] if others else []
    return chosen.rel, note


def _resolution(path: Path) -> tuple[int, int] | None:
    """(width, height) from the image header, without decoding pixels; None if it cannot be read."""
    try:
        header = read_header(path)
    except MaterialError:
        return None
    return header.width, header.height


def _flag_shared_outputs(materials: list[FoundMaterial]) -> None:
    """Two materials with one output folder (a folder `Wood/` next to `Wood_BaseColor.png`) would overwrite each
    other: both get a problem. Compared case-insensitively, as Windows and macOS file systems do."""
    by_output: dict[str, list[FoundMaterial]] = {}
    for found in materials:
        by_output.setdefault(found.output.lower(), []).append(found)
    for shared in by_output.values():
        for found in shared if len(shared) > 1 else []:
            others = [other.material for other in shared if other is not found]
            found.problems.append(f"output folder '{found.output}' is also the output of "
                                  f"{join_names(others)}; rename or move one")
