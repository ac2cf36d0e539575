"""Texture-set input: image files -> a validated, normalised 8-channel material array.

Three steps, each usable on its own:

1. `discover_material(folder)` assigns files to roles (albedo, normal, ARM or separate AO / roughness /
   metalness) from their names, the way Poly Haven, ambientCG, 3dtextures.me, Substance Painter, Unreal (`T_x_D`,
   `_N`, `_ORM`), glTF and generic exporters name them.
2. `resolve_material(folder, explicit)` lets files named on the command line override what was discovered and
   checks that the set is complete (albedo, normal and roughness are required).
3. `load_texture_set(files)` reads and validates the images and packs them into one (H, W, 8) float32 array
   in the order of `CHANNELS`; `load_material` does 2 and 3 in one call.

Values are kept as stored: albedo stays sRGB-encoded, the normal's x and y stay (n + 1) / 2 in the source's
convention (not flipped to OpenGL; the convention travels in `MaterialSource.normal_convention`), AO,
roughness and metalness are linear [0, 1]. Every problem with the input raises `MaterialError`, a ValueError
whose message is one line naming the file (or folder) and the problem.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np
import OpenImageIO as oiio
import pydantic

from .images import ImageReadError, read_image

__all__ = [
    "CHANNELS", "IMAGE_EXTENSIONS", "TEXTURES", "MaterialError", "MaterialFiles", "MaterialSource",
    "NormalConvention", "Role", "SourceFile", "TextureSet", "discover_material", "file_sha256", "load_material",
    "load_texture_set", "material_images", "normal_convention_from_name", "resolve_material",
]

Role = Literal["albedo", "normal", "arm", "ao", "roughness", "metalness"]
NormalConvention = Literal["opengl", "directx"]
# Maps bcf does not compress but an asset scan still lists with their material (`bcf.core.assets`).
ExtraRole = Literal["height", "opacity"]

ROLES: tuple[Role, ...] = get_args(Role)
# The maps an ARM (or glTF ORM) texture packs, in its channel order R, G, B.
PACKED_ROLES: tuple[Role, ...] = ("ao", "roughness", "metalness")

CHANNELS = ("albedo_r", "albedo_g", "albedo_b", "normal_x", "normal_y", "ao", "roughness", "metalness")
# Where each texture of the compressed material lives in the channel axis of `TextureSet.channels`.
TEXTURES: dict[str, slice] = {"albedo": slice(0, 3), "normal": slice(3, 5), "arm": slice(5, 8)}
_CHANNEL_OF: dict[Role, int] = {"ao": 5, "roughness": 6, "metalness": 7}

# Constants for maps a material may lack: no AO means nothing is occluded, no metalness means a dielectric.
DEFAULTS: dict[Role, float] = {"ao": 1.0, "metalness": 0.0}

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".tga", ".tif", ".tiff", ".exr"})
MIN_SIZE = 64

# The command-line options the messages point to (the CLI defines them; named here so messages agree).
_ROLE_OPTIONS = "--albedo/--normal/--arm/--roughness"
_CONVENTION_OPTION = "--normal-convention"


class MaterialError(ValueError):
    """Bad material input; str(exc) is one line naming the file (or folder) and the problem."""


# ------------------------------------------------------------------------------------------------ models


class MaterialFiles(pydantic.BaseModel):
    """Which file plays which role. `arm` and the separate `ao`/`roughness`/`metalness` exclude each other."""

    model_config = pydantic.ConfigDict(extra="forbid")

    albedo: Path | None = None
    normal: Path | None = None
    arm: Path | None = None
    ao: Path | None = None
    roughness: Path | None = None
    metalness: Path | None = None
    normal_convention: NormalConvention | None = None  # None: unknown (load assumes opengl and adds a note)
    ignored: list[Path] = []  # files found in the folder that play no role (height, opacity, ...)
    notes: list[str] = []  # choices discovery made, to show the user

    def roles(self) -> dict[Role, Path]:
        """The roles that have a file, in `ROLES` order."""
        return {role: path for role in ROLES if (path := getattr(self, role)) is not None}


class SourceFile(pydantic.BaseModel):
    """One input file as the manifest records it."""

    model_config = pydantic.ConfigDict(extra="forbid")

    role: Role
    name: str  # file name only, no folder: the manifest must not leak local paths
    sha256: str  # of the file's bytes
    channels: int
    width: int
    height: int
    format: str  # OpenImageIO format name: "png", "jpeg", "openexr", "targa", "tiff"
    bits: str  # OpenImageIO pixel type: "uint8", "uint16", "half", "float", ...


class MaterialSource(pydantic.BaseModel):
    """Description of the input texture set, stored in the compressed output's manifest."""

    model_config = pydantic.ConfigDict(extra="forbid")

    name: str  # folder name, or the albedo file's stem when there is no folder
    width: int
    height: int
    normal_convention: NormalConvention
    arm_packed: bool
    files: list[SourceFile]
    defaults: dict[str, float]  # roles filled with constants, e.g. {"ao": 1.0} or {"metalness": 0.0}


@dataclass(frozen=True)
class TextureSet:
    """A loaded material.

    channels: (H, W, 8) float32 in [0, 1], in `CHANNELS` order, values as stored (see the module docstring).
    notes: non-fatal observations for the user (discovery choices first, then loading ones).
    """

    channels: np.ndarray
    source: MaterialSource
    notes: tuple[str, ...]

    @property
    def width(self) -> int:
        return int(self.channels.shape[1])

    @property
    def height(self) -> int:
        return int(self.channels.shape[0])


# --------------------------------------------------------------------------------------------- naming

# Name suffixes (as lower-case tokens, after trailing noise is dropped) -> role and, for normals, the convention
# the name states. A file matches the first entry equal to the last tokens of its name; multi-token entries
# are listed first.
_SUFFIXES: tuple[tuple[tuple[str, ...], Role, NormalConvention | None], ...] = (
    (("nor", "gl"), "normal", "opengl"),  # Poly Haven
    (("nor", "dx"), "normal", "directx"),
    (("normal", "gl"), "normal", "opengl"),
    (("normal", "dx"), "normal", "directx"),
    (("normal", "opengl"), "normal", "opengl"),
    (("normal", "directx"), "normal", "directx"),
    (("base", "color"), "albedo", None),
    (("base", "colour"), "albedo", None),
    (("ambient", "occlusion"), "ao", None),
    (("mixed", "ao"), "ao", None),  # Substance Painter's `_Mixed_AO`
    (("occlusion", "roughness", "metallic"), "arm", None),
    (("normalgl",), "normal", "opengl"),  # ambientCG
    (("normaldx",), "normal", "directx"),
    (("normal",), "normal", None),
    (("nor",), "normal", None),
    (("diff",), "albedo", None),  # Poly Haven
    (("col",), "albedo", None),
    (("color",), "albedo", None),  # ambientCG
    (("colour",), "albedo", None),
    (("basecolor",), "albedo", None),  # also Substance Painter's `_BaseColor` (one token)
    (("basecolour",), "albedo", None),
    (("albedo",), "albedo", None),
    (("diffuse",), "albedo", None),
    (("bc",), "albedo", None),  # Unreal base colour
    (("d",), "albedo", None),  # Unreal diffuse
    # Unreal's `_N`: the engine's tangent space is DirectX-style (Y-), so its normal maps are stored that way.
    (("n",), "normal", "directx"),
    (("arm",), "arm", None),
    (("orm",), "arm", None),  # glTF occlusion-roughness-metallic: the same channel order as ARM
    (("occlusionroughnessmetallic",), "arm", None),  # Substance Painter / glTF exporters, spelled out
    # Not MRA (metallic-roughness-AO): its channel order differs from ARM's.
    (("ambientocclusion",), "ao", None),
    (("occlusion",), "ao", None),
    (("ao",), "ao", None),
    (("rough",), "roughness", None),
    (("roughness",), "roughness", None),
    (("metal",), "metalness", None),
    (("metalness",), "metalness", None),
    (("metallic",), "metalness", None),
)

# Maps a material folder often holds that bcf does not use.
_UNUSED = frozenset({
    "displacement", "disp", "height", "opacity", "alpha", "bump", "specular", "spec", "emissive", "emission",
    "preview", "thumbnail", "gloss", "glossiness", "mask", "transmission", "translucency", "idmask",
    "transparency",
})
# The unused maps an asset scan lists with their material (the rest of `_UNUSED` it leaves out).
_EXTRA_MAPS: dict[str, ExtraRole] = {
    "height": "height", "displacement": "height", "disp": "height", "bump": "height",
    "opacity": "opacity", "alpha": "opacity", "transparency": "opacity",
}

# Tokens that can trail the map name: resolutions (2k, 1K), formats (ambientCG's "1K-JPG"), Poly Haven's
# variant numbers (`col_1`) and generic words. They never decide a role.
_NOISE = re.compile(r"\d+k|\d+|jpe?g|png|exr|tga|tiff?|map|tex|texture")
_SEPARATORS = re.compile(r"[_\-.\s]+")

# ambientCG's old (cc0textures) naming `<Name>_<N>K[-FMT]_Normal`: those sets shipped a single normal map and it
# is DirectX; newer sets name both `_NormalGL` and `_NormalDX`. Both such files in our reference collection
# (Metal009_2K_Normal, Chainmail004_1K_Normal) measure as DirectX against their height maps (see
# tests/data/README.md), so the name is evidence enough; a note still tells the user how to override it.
_AMBIENTCG_PLAIN_NORMAL = re.compile(r"[a-z0-9]+_\d+k(-[a-z]+)?_normal", re.IGNORECASE)


@dataclass(frozen=True)
class _Named:
    """What a file name says: a role (None: no role), and for a normal map its convention if the name tells."""

    role: Role | None
    convention: NormalConvention | None = None
    unused: bool = False  # a known map bcf does not use (height, opacity, ...), as opposed to an unknown name
    extra: ExtraRole | None = None  # for an unused map: height or opacity, the kinds an asset scan lists
    prefix: int = 0  # how many leading tokens of the name come before the map's name (the material's name)


def _tokens(stem: str) -> list[str]:
    """Lower-case tokens of a file stem, split on `_`, `-`, `.` and white space, trailing noise removed."""
    tokens = [token for token in _SEPARATORS.split(stem.lower()) if token]
    while tokens and _NOISE.fullmatch(tokens[-1]):
        tokens.pop()
    return tokens


def _classify(path: Path) -> _Named:
    """The role a file's name gives it. Only the end of the name counts (after resolution and format tokens),
    so a material called e.g. `rusty_metal_02` does not make every one of its files a metalness map."""
    if path.suffix.lower() not in IMAGE_EXTENSIONS:
        return _Named(None, unused=True)
    tokens = _tokens(path.stem)
    if tokens and tokens[-1] in _UNUSED:
        return _Named(None, unused=True, extra=_EXTRA_MAPS.get(tokens[-1]), prefix=len(tokens) - 1)
    for suffix, role, convention in _SUFFIXES:
        # A single letter is a map name only after a material name (Unreal's `T_Brick_N`), not alone (`n.png`).
        if len(suffix[0]) == 1 and len(tokens) == 1:
            continue
        if tuple(tokens[-len(suffix):]) == suffix:
            if role == "normal" and convention is None and _AMBIENTCG_PLAIN_NORMAL.fullmatch(path.stem):
                convention = "directx"
            return _Named(role, convention, prefix=max(len(tokens) - len(suffix), 0))
    return _Named(None)


def _convention_from_name(path: Path) -> NormalConvention | None:
    """The normal-map convention `path`'s name states, None when it does not."""
    named = _classify(path)
    return named.convention if named.role == "normal" else None


def normal_convention_from_name(name: str) -> NormalConvention | None:
    """The convention a normal map's file name states (`_nor_gl`, `_NormalDX`, ambientCG's plain `_Normal`, ...)."""
    return _convention_from_name(Path(name))


def _plain_ambientcg_note(path: Path) -> str:
    return (f"{path.name}: ambientCG's plain '_Normal' maps are DirectX; treating it as DirectX "
            f"(pass {_CONVENTION_OPTION} opengl if it is not)")


# ------------------------------------------------------------------------------------------ discovery


@dataclass
class _Scan:
    """A folder's files sorted by what their names say: candidates per role, and the rest."""

    candidates: dict[Role, list[tuple[Path, NormalConvention | None]]]
    ignored: list[Path]
    unknown_images: list[Path]  # image files whose name matches no role (worth telling the user about)


def _scan(directory: Path) -> _Scan:
    """Classify every file of `directory` (not recursive). Raises MaterialError for a missing or empty folder."""
    if not directory.exists():
        raise MaterialError(f"{directory}: no such folder")
    if not directory.is_dir():
        raise MaterialError(f"{directory}: not a folder")
    files = sorted((p for p in directory.iterdir() if p.is_file()), key=lambda p: p.name)
    if not files:
        raise MaterialError(f"{directory}: the folder has no files")
    return _scan_files(files)


def _scan_files(files: Iterable[Path]) -> _Scan:
    """Classify `files` (in the given order): `_scan` for a folder, or an asset scan for part of one."""
    scan = _Scan(candidates={role: [] for role in ROLES}, ignored=[], unknown_images=[])
    for path in files:
        named = _classify(path)
        if named.role is not None:
            scan.candidates[named.role].append((path, named.convention))
        else:
            scan.ignored.append(path)
            if not named.unused:
                scan.unknown_images.append(path)
    return scan


def _pick(directory: Path, role: Role, candidates: list[tuple[Path, NormalConvention | None]],
          convention: NormalConvention | None) -> tuple[Path, NormalConvention | None, list[str]]:
    """The one file for `role` among `candidates` (non-empty): (file, its convention, notes).

    `convention` is the normal convention the user asked for (None: not given). Several candidates are an
    error naming them all, except OpenGL and DirectX versions of one normal map: the one in the asked-for
    convention is taken, OpenGL when none was asked for, since both describe the same surface.
    """
    if len(candidates) == 1:
        path, named = candidates[0]
        plain = role == "normal" and named == "directx" and _AMBIENTCG_PLAIN_NORMAL.fullmatch(path.stem)
        # Only worth saying when the convention was inferred and the user did not settle it.
        return path, named, [_plain_ambientcg_note(path)] if plain and convention is None else []
    if role == "normal" and all(named is not None for _, named in candidates):
        wanted = convention or "opengl"
        chosen = [path for path, named in candidates if named == wanted]
        if len(chosen) == 1:
            others = [path for path, named in candidates if named != wanted]
            label = {"opengl": "OpenGL", "directx": "DirectX"}
            note = (f"both OpenGL and DirectX normal maps found; using {label[wanted]} {chosen[0].name}, "
                    f"ignoring {_join(p.name for p in others)}")
            return chosen[0], wanted, [note]
    raise MaterialError(f"{directory}: {len(candidates)} files could be the {role} map: "
                        f"{_join(path.name for path, _ in candidates)}; remove all but one or name it with --{role}")


def _join(names: Iterable[str]) -> str:
    """'a', 'a and b', 'a, b and c'."""
    items = list(names)
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


def _choose(directory: Path, scan: _Scan, skip: frozenset[Role] = frozenset(),
            convention: NormalConvention | None = None, problems: list[str] | None = None) -> MaterialFiles:
    """One file per role from `scan`, leaving out the roles in `skip` (the caller has files for them);
    `convention` is the normal convention the user asked for, if any (see `_pick`).

    A role with several candidates raises MaterialError, or, when `problems` is given, appends the error's
    message there and leaves the role empty, so a scan of many folders can report it and go on."""
    chosen: dict[Role, Path] = {}
    normal_convention: NormalConvention | None = None
    ignored = list(scan.ignored)
    notes: list[str] = []
    for role in ROLES:
        candidates = scan.candidates[role]
        if role in skip:
            ignored.extend(path for path, _ in candidates)
            continue
        if not candidates:
            continue
        try:
            path, role_convention, role_notes = _pick(directory, role, candidates, convention)
        except MaterialError as exc:
            if problems is None:
                raise
            problems.append(str(exc))
            ignored.extend(p for p, _ in candidates)
            continue
        chosen[role] = path
        notes.extend(role_notes)
        ignored.extend(p for p, _ in candidates if p != path)
        if role == "normal":
            normal_convention = role_convention
    if "arm" in chosen:
        # A packed ARM map and separate maps for the same channels: the ARM map is the usual delivery format
        # (Poly Haven ships both), and mixing would be ambiguous, so the ARM map wins.
        separate = [chosen.pop(role) for role in PACKED_ROLES if role in chosen]
        if separate:
            ignored.extend(separate)
            notes.append(f"using the ARM map {chosen['arm'].name} for AO, roughness and metalness; ignoring "
                         f"{_join(p.name for p in separate)}")
    if scan.unknown_images:
        notes.append(f"ignoring images whose names match no role: {_join(p.name for p in scan.unknown_images)}")
    return MaterialFiles(**chosen, normal_convention=normal_convention, ignored=sorted(ignored), notes=notes)


def discover_material(directory: Path) -> MaterialFiles:
    """Assign the files of `directory` to roles by their names (case-insensitive, on the file stem).

    Does not check completeness (see `resolve_material`). Raises MaterialError for a missing, non-folder or
    empty `directory` and for two files that could play the same role.
    """
    directory = Path(directory)
    return _choose(directory, _scan(directory))


# ----------------------------------------------------------------------------------------- resolution


def resolve_material(directory: Path | None, explicit: MaterialFiles) -> MaterialFiles:
    """Files named explicitly (command-line options) override the ones discovered in `directory`.

    `directory=None` uses `explicit` alone. An explicit ARM map replaces discovered separate AO / roughness /
    metalness maps and vice versa; naming --arm together with --ao/--roughness/--metalness is an error. The
    normal convention is the explicit one, else the one the chosen normal file's name states, else None.
    Raises MaterialError for a folder problem, an explicit file that does not exist, or an incomplete set.
    """
    given = explicit.roles()
    separate = [role for role in PACKED_ROLES if role in given]
    if "arm" in given and separate:
        raise MaterialError(f"{given['arm']}: --arm cannot be combined with "
                            f"{_join('--' + r for r in separate)}: the ARM map already holds AO, roughness and "
                            f"metalness")
    for role, path in given.items():
        if not Path(path).is_file():
            raise MaterialError(f"{path}: no such file (given as --{role})")
    notes = list(explicit.notes)
    if directory is None:
        found = MaterialFiles()
    else:
        # Roles given explicitly are not discovered, so duplicates there do not matter; an explicit ARM map
        # (or separate map) excludes the other packing too.
        scan = _scan(Path(directory))
        excluded: set[Role] = set(PACKED_ROLES) if "arm" in given else {"arm"} if separate else set()
        found = _choose(Path(directory), scan, frozenset(set(given) | excluded), explicit.normal_convention)
        dropped = [path for role in sorted(excluded) for path, _ in scan.candidates[role]]
        if dropped:
            reason = "--arm" if "arm" in given else _join("--" + r for r in PACKED_ROLES if r in given)
            notes.append(f"ignoring {_join(p.name for p in dropped)}: {reason} given")
        notes = found.notes + notes
    roles = {**found.roles(), **given}
    if explicit.normal_convention is not None:
        convention = explicit.normal_convention
    elif "normal" in given:
        convention = _convention_from_name(Path(given["normal"]))
        if convention == "directx" and _AMBIENTCG_PLAIN_NORMAL.fullmatch(Path(given["normal"]).stem):
            notes.append(_plain_ambientcg_note(Path(given["normal"])))
    else:
        convention = found.normal_convention
    # Compare resolved paths: an explicit `./x.png` and the discovered `folder/x.png` may be the same file.
    used = {Path(path).resolve() for path in roles.values()}
    ignored = sorted({p for p in [*found.ignored, *explicit.ignored] if Path(p).resolve() not in used})
    resolved = MaterialFiles(**roles, normal_convention=convention, ignored=ignored, notes=notes)
    _check_complete(resolved, directory)
    return resolved


def _missing_roles(roles: Iterable[Role]) -> list[str]:
    """The required roles absent from `roles`, as messages name them: albedo, normal, roughness (or an ARM map)."""
    present = set(roles)
    missing = [role for role in ("albedo", "normal") if role not in present]
    if "arm" not in present and "roughness" not in present:
        missing.append("roughness (or an ARM map)")
    return missing


def _check_complete(files: MaterialFiles, directory: Path | None) -> None:
    """Raise MaterialError unless `files` has albedo, normal and roughness (own file or ARM), ARM exclusive."""
    roles = files.roles()
    packed = [role for role in PACKED_ROLES if role in roles]
    # Name the folder the user gave, else the one the files are in, so the message says which material.
    where = str(directory) if directory is not None else str(next(iter(roles.values())).parent) if roles \
        else "material"
    if "arm" in roles and packed:
        raise MaterialError(f"{where}: an ARM map ({roles['arm'].name}) and separate "
                            f"{'/'.join(packed)} maps cannot be used together")
    missing = _missing_roles(roles)
    if missing:
        found = ", ".join(f"{role} {path.name}" for role, path in roles.items()) or "nothing"
        raise MaterialError(f"{where}: incomplete material: found {found}; missing {', '.join(missing)}; "
                            f"name the files with {_ROLE_OPTIONS}")


# -------------------------------------------------------------------------------------------- loading


@dataclass(frozen=True)
class _Header:
    """What OpenImageIO says about a file without decoding its pixels."""

    width: int
    height: int
    channels: int
    format: str
    bits: str


def _read_header(path: Path) -> _Header:
    """Open `path` and read its header only, so size and channel problems surface before any decoding."""
    if not path.is_file():
        raise MaterialError(f"{path}: no such file")
    image_input = oiio.ImageInput.open(str(path))
    if image_input is None:
        problem = _one_line(oiio.geterror()) or "unknown OpenImageIO error"
        raise MaterialError(f"{path}: cannot read image: {problem}")
    try:
        spec = image_input.spec()
        return _Header(spec.width, spec.height, spec.nchannels, image_input.format_name(), str(spec.format))
    finally:
        image_input.close()


def _check_channels(role: Role, path: Path, channels: int) -> None:
    """Raise MaterialError if a `role` file with `channels` channels cannot be used."""
    if role == "albedo" and channels < 3:
        raise MaterialError(f"{path}: albedo needs 3 channels (RGB), found {channels}")
    if role == "normal" and channels < 2:
        raise MaterialError(f"{path}: normal needs 2 or 3 channels (XY or XYZ), found {channels}")
    if role == "arm" and channels < 3:
        raise MaterialError(f"{path}: arm needs 3 channels (R = AO, G = roughness, B = metalness), found {channels}")
    if role in PACKED_ROLES and channels == 2:
        raise MaterialError(f"{path}: {role} needs 1 channel (grey) or 3 (RGB, R is used), found {channels}")


def _check_sizes(headers: dict[Role, tuple[Path, _Header]]) -> tuple[int, int]:
    """The common (width, height) of all files; MaterialError if they differ or it is not usable."""
    sizes = {(h.width, h.height) for _, h in headers.values()}
    if len(sizes) > 1:
        listing = ", ".join(f"{path} {h.width}x{h.height}" for path, h in headers.values())
        raise MaterialError(f"the files differ in size: {listing}; all must be the same size")
    width, height = sizes.pop()
    if not (_usable_side(width) and _usable_side(height)):
        path = headers["albedo"][0] if "albedo" in headers else next(iter(headers.values()))[0]
        raise MaterialError(f"{path}: size {width}x{height} is not supported: width and height must each be "
                            f"a power of two and at least {MIN_SIZE}")
    return width, height


def _usable_side(n: int) -> bool:
    return n >= MIN_SIZE and n & (n - 1) == 0


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes, as `SourceFile.sha256` records it (a batch compares it to skip unchanged inputs)."""
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        for chunk in iter(lambda: stream.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _read_pixels(path: Path) -> np.ndarray:
    """(h, w, c) float32 of `path`, every stored channel; MaterialError naming the file on any read problem."""
    try:
        return read_image(path)
    except ImageReadError as exc:
        raise MaterialError(_one_line(str(exc))) from None


def _one_line(text: str) -> str:
    """OpenImageIO's messages can span lines (one per library layer); MaterialError promises one line."""
    return "; ".join(line.strip() for line in text.splitlines() if line.strip())


def _used_channels(role: Role, path: Path, pixels: np.ndarray, notes: list[str]) -> np.ndarray:
    """The channels of a `role` file that go into the material: (h, w, k) with k = 3, 2, 3 or 1 for albedo,
    normal, arm and a single map. Adds a note for what is dropped when it may matter."""
    channels = pixels.shape[2]
    if role == "albedo":
        if channels > 3:
            notes.append(f"{path.name}: albedo alpha channel ignored")
        return pixels[..., :3]
    if role == "normal":
        return pixels[..., :2]  # z is implied by x and y of a unit normal
    if role == "arm":
        if channels > 3:
            notes.append(f"{path.name}: ARM channel 4 (alpha) ignored")
        return pixels[..., :3]
    if channels >= 3:
        # Grey maps are often saved as RGB; only warn if it is not actually grey (beyond rounding).
        spread = float(np.max(np.ptp(pixels[..., :3], axis=2)))
        if spread > 1.5 / 255:
            notes.append(f"{path.name}: {role} stored as RGB with differing channels (up to {spread:.3f} apart); "
                         f"using channel 0 (R)")
    return pixels[..., :1]


def _clip(path: Path, values: np.ndarray, notes: list[str]) -> np.ndarray:
    """`values` limited to [0, 1] (float formats may hold anything, signed integers read as [-1, 1]), with a
    note counting the values changed; NaN has no sensible replacement and is an error."""
    if np.isnan(values).any():
        raise MaterialError(f"{path}: {int(np.isnan(values).sum())} values are NaN")
    outside = int(np.count_nonzero((values < 0.0) | (values > 1.0)))
    if outside:
        notes.append(f"{path.name}: {outside} values outside [0, 1] clipped")
        return np.clip(values, 0.0, 1.0)
    return values


def load_texture_set(files: MaterialFiles, name: str | None = None) -> TextureSet:
    """Read and validate the files of `files` into a TextureSet.

    `name` defaults to the albedo file's stem. Checks, in order (all before decoding any pixels except the
    last two): completeness, readable headers, channel counts per role, equal sizes, power-of-two sizes
    >= 64, then decodes (truncated or corrupt data is an error) and clips values outside [0, 1] with a note.
    Missing AO becomes 1 and missing metalness 0 (recorded in `source.defaults`, with a note).
    """
    _check_complete(files, None)
    roles = files.roles()
    headers: dict[Role, tuple[Path, _Header]] = {}
    for role, path in roles.items():
        header = _read_header(Path(path))
        _check_channels(role, Path(path), header.channels)
        headers[role] = (Path(path), header)
    width, height = _check_sizes(headers)

    notes: list[str] = list(files.notes)
    channels = np.empty((height, width, len(CHANNELS)), dtype=np.float32)
    for role, (path, header) in headers.items():
        used = _used_channels(role, path, _read_pixels(path), notes)
        if not header.bits.startswith("uint"):  # OIIO maps unsigned integers into [0, 1] already: skip the scan
            used = _clip(path, used, notes)
        target = TEXTURES[role] if role in TEXTURES else slice(_CHANNEL_OF[role], _CHANNEL_OF[role] + 1)
        channels[..., target] = used

    defaults: dict[str, float] = {}
    if "arm" not in roles:
        for role, value in DEFAULTS.items():
            if role not in roles:
                channels[..., _CHANNEL_OF[role]] = value
                defaults[role] = value
                notes.append(f"no {role} map: using the constant {value:g}")

    convention = files.normal_convention
    if convention is None:
        convention = "opengl"
        notes.append(f"{roles['normal'].name}: normal map convention not known from its name; assuming OpenGL "
                     f"(Y+), pass {_CONVENTION_OPTION} directx if it is DirectX (Y-)")

    source = MaterialSource(
        name=name if name is not None else roles["albedo"].stem,
        width=width,
        height=height,
        normal_convention=convention,
        arm_packed="arm" in roles,
        files=[SourceFile(role=role, name=path.name, sha256=file_sha256(path), channels=h.channels, width=h.width,
                          height=h.height, format=h.format, bits=h.bits) for role, (path, h) in headers.items()],
        defaults=defaults,
    )
    return TextureSet(channels=channels, source=source, notes=tuple(notes))


def load_material(directory: Path | None, explicit: MaterialFiles | None = None) -> TextureSet:
    """`resolve_material` then `load_texture_set`; the material is named after `directory` when given."""
    files = resolve_material(None if directory is None else Path(directory), explicit or MaterialFiles())
    return load_texture_set(files, name=None if directory is None else Path(directory).resolve().name)


def material_images(channels: np.ndarray) -> dict[str, np.ndarray]:
    """(h, w, 8) decoded material -> albedo, normal (z rebuilt), ARM as (h, w, 3) images in [0, 1]."""
    channels = np.clip(channels, 0.0, 1.0)
    xy = channels[..., 3:5] * 2.0 - 1.0
    z = np.sqrt(np.clip(1.0 - (xy**2).sum(-1, keepdims=True), 0.0, 1.0))
    return {"albedo": channels[..., 0:3], "normal": np.concatenate([channels[..., 3:5], (z + 1.0) / 2.0], -1),
            "arm": channels[..., 5:8]}
