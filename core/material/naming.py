"""File names -> roles: discovery of a material folder's textures and the resolution of explicitly named files.

`discover_material(folder)` assigns files to roles (albedo, normal, ARM or separate AO / roughness / metalness)
from their names, the way Poly Haven, ambientCG, 3dtextures.me, Substance Painter, Unreal (`T_x_D`, `_N`,
`_ORM`), glTF and generic exporters name them. `resolve_material(folder, explicit)` lets explicitly named files
override what was discovered and checks that the set is complete (albedo, normal and roughness are required).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from bcf.core.material.roles import (IMAGE_EXTENSIONS, PACKED_ROLES, ROLES, ExtraRole, MaterialError, MaterialFiles,
                                     NormalConvention, Role)

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
NOISE_TOKENS = re.compile(r"\d+k|\d+|jpe?g|png|exr|tga|tiff?|map|tex|texture")
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
    while tokens and NOISE_TOKENS.fullmatch(tokens[-1]):
        tokens.pop()
    return tokens


def classify_name(path: Path) -> _Named:
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
    named = classify_name(path)
    return named.convention if named.role == "normal" else None


def normal_convention_from_name(name: str) -> NormalConvention | None:
    """The convention a normal map's file name states (`_nor_gl`, `_NormalDX`, ambientCG's plain `_Normal`, ...)."""
    return _convention_from_name(Path(name))


def _plain_ambientcg_note(path: Path) -> str:
    return (f"{path.name}: ambientCG's plain '_Normal' maps are DirectX; treating it as DirectX "
            f"(set the normal convention to opengl if it is not)")


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
        raise MaterialError("no such folder", file=directory)
    if not directory.is_dir():
        raise MaterialError("not a folder", file=directory)
    files = sorted((p for p in directory.iterdir() if p.is_file()), key=lambda p: p.name)
    if not files:
        raise MaterialError("the folder has no files", file=directory)
    return scan_files(files)


def scan_files(files: Iterable[Path]) -> _Scan:
    """Classify `files` (in the given order): `_scan` for a folder, or an asset scan for part of one."""
    scan = _Scan(candidates={role: [] for role in ROLES}, ignored=[], unknown_images=[])
    for path in files:
        named = classify_name(path)
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
                    f"ignoring {join_names(p.name for p in others)}")
            return chosen[0], wanted, [note]
    raise MaterialError(f"{len(candidates)} files could be the {role} map: "
                        f"{join_names(path.name for path, _ in candidates)}", file=directory, role=role,
                        fix="remove all but one or name it with {}", options=[role])


def join_names(names: Iterable[str]) -> str:
    """'a', 'a and b', 'a, b and c'."""
    items = list(names)
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


def choose_roles(directory: Path, scan: _Scan, skip: frozenset[Role] = frozenset(),
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
                         f"{join_names(p.name for p in separate)}")
    if scan.unknown_images:
        notes.append(f"ignoring images whose names match no role: {join_names(p.name for p in scan.unknown_images)}")
    return MaterialFiles(**chosen, normal_convention=normal_convention, ignored=sorted(ignored), notes=notes)


def discover_material(directory: Path) -> MaterialFiles:
    """Assign the files of `directory` to roles by their names (case-insensitive, on the file stem).

    Does not check completeness (see `resolve_material`). Raises MaterialError for a missing, non-folder or
    empty `directory` and for two files that could play the same role.
    """
    directory = Path(directory)
    return choose_roles(directory, _scan(directory))


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
        raise MaterialError("{} cannot be combined with {}: the ARM map already holds AO, roughness and "
                            "metalness", file=given["arm"], role="arm", options=["arm", separate])
    for role, path in given.items():
        if not Path(path).is_file():
            raise MaterialError("no such file (given as {})", file=path, role=role, options=[role])
    notes = list(explicit.notes)
    if directory is None:
        found = MaterialFiles()
    else:
        # Roles given explicitly are not discovered, so duplicates there do not matter; an explicit ARM map
        # (or separate map) excludes the other packing too.
        scan = _scan(Path(directory))
        excluded: set[Role] = set(PACKED_ROLES) if "arm" in given else {"arm"} if separate else set()
        found = choose_roles(Path(directory), scan, frozenset(set(given) | excluded), explicit.normal_convention)
        dropped = [path for role in sorted(excluded) for path, _ in scan.candidates[role]]
        if dropped:
            reason = "an ARM map" if "arm" in given else join_names(r for r in PACKED_ROLES if r in given) + " maps"
            notes.append(f"ignoring {join_names(p.name for p in dropped)}: {reason} given explicitly")
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
    check_complete(resolved, directory)
    return resolved


def missing_roles(roles: Iterable[Role]) -> list[str]:
    """The required roles absent from `roles`, as messages name them: albedo, normal, roughness (or an ARM map)."""
    present = set(roles)
    missing = [role for role in ("albedo", "normal") if role not in present]
    if "arm" not in present and "roughness" not in present:
        missing.append("roughness (or an ARM map)")
    return missing


def check_complete(files: MaterialFiles, directory: Path | None) -> None:
    """Raise MaterialError unless `files` has albedo, normal and roughness (own file or ARM), ARM exclusive."""
    roles = files.roles()
    packed = [role for role in PACKED_ROLES if role in roles]
    # Name the folder the user gave, else the one the files are in, so the message says which material.
    where = str(directory) if directory is not None else str(next(iter(roles.values())).parent) if roles \
        else "material"
    if "arm" in roles and packed:
        raise MaterialError(f"an ARM map ({roles['arm'].name}) and separate {'/'.join(packed)} maps cannot be "
                            "used together", file=where, role="arm")
    missing = missing_roles(roles)
    if missing:
        found = ", ".join(f"{role} {path.name}" for role, path in roles.items()) or "nothing"
        raise MaterialError(f"incomplete material: found {found}; missing {', '.join(missing)}; "
                            "name the files with {}", file=where, options=[("albedo", "normal", "arm", "roughness")])


