"""Texture-set loading: the files of a `MaterialFiles` -> a validated, normalised (H, W, 8) float32 array.

Checks, in order, all before decoding any pixels except the last two: completeness, readable headers, channel
counts per role, equal sizes, power-of-two sizes >= 64, then decoding (truncated or corrupt data is an error)
and clipping of values outside [0, 1] with a note. Every problem raises `MaterialError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pydantic

from bcf.core.files import file_sha256
from bcf.core.material.images import ImageReadError, read_image
from bcf.core.material.naming import check_complete, resolve_material
from bcf.core.material.roles import (CHANNEL_OF, CHANNELS, DEFAULTS, MIN_SIZE, PACKED_ROLES, TEXTURES, MaterialError,
                                     MaterialFiles, NormalConvention, Role)


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


# -------------------------------------------------------------------------------------------- loading


@dataclass(frozen=True)
class _Header:
    """What OpenImageIO says about a file without decoding its pixels."""

    width: int
    height: int
    channels: int
    format: str
    bits: str


def read_header(path: Path) -> _Header:
    """Open `path` and read its header only, so size and channel problems surface before any decoding."""
    if not path.is_file():
        raise MaterialError("no such file", file=path)
    image_input = oiio.ImageInput.open(str(path))
    if image_input is None:
        problem = _one_line(oiio.geterror()) or "unknown OpenImageIO error"
        raise MaterialError(f"cannot read image: {problem}", file=path)
    try:
        spec = image_input.spec()
        return _Header(spec.width, spec.height, spec.nchannels, image_input.format_name(), str(spec.format))
    finally:
        image_input.close()


def _check_channels(role: Role, path: Path, channels: int) -> None:
    """Raise MaterialError if a `role` file with `channels` channels cannot be used."""
    if role == "albedo" and channels < 3:
        raise MaterialError(f"albedo needs 3 channels (RGB), found {channels}", file=path, role=role)
    if role == "normal" and channels < 2:
        raise MaterialError(f"normal needs 2 or 3 channels (XY or XYZ), found {channels}", file=path, role=role)
    if role == "arm" and channels < 3:
        raise MaterialError(f"arm needs 3 channels (R = AO, G = roughness, B = metalness), found {channels}",
                            file=path, role=role)
    if role in PACKED_ROLES and channels == 2:
        raise MaterialError(f"{role} needs 1 channel (grey) or 3 (RGB, R is used), found {channels}", file=path,
                            role=role)


def _check_pixels(path: Path, header: _Header, max_pixels: int) -> None:
    """MaterialError for an image larger than `max_pixels`, from its header: a small file may claim a huge
    size (a decompression bomb), so this comes before any pixel is decoded."""
    pixels = header.width * header.height
    if pixels > max_pixels:
        raise MaterialError(f"{header.width}x{header.height} is {pixels:,} pixels, more than the limit of "
                            f"{max_pixels:,}", file=path)


def _check_sizes(headers: dict[Role, tuple[Path, _Header]]) -> tuple[int, int]:
    """The common (width, height) of all files; MaterialError if they differ or it is not usable."""
    sizes = {(h.width, h.height) for _, h in headers.values()}
    if len(sizes) > 1:
        listing = ", ".join(f"{path.name} {h.width}x{h.height}" for path, h in headers.values())
        first = next(iter(headers.values()))[1]
        odd = next(path for path, h in headers.values() if (h.width, h.height) != (first.width, first.height))
        raise MaterialError(f"the files differ in size: {listing}; all must be the same size", file=odd)
    width, height = sizes.pop()
    if not (_usable_side(width) and _usable_side(height)):
        path = headers["albedo"][0] if "albedo" in headers else next(iter(headers.values()))[0]
        raise MaterialError(f"size {width}x{height} is not supported: width and height must each be a power of two "
                            f"and at least {MIN_SIZE}", file=path)
    return width, height


def _usable_side(n: int) -> bool:
    return n >= MIN_SIZE and n & (n - 1) == 0


def _read_pixels(path: Path) -> np.ndarray:
    """(h, w, c) float32 of `path`, every stored channel; MaterialError naming the file on any read problem."""
    try:
        return read_image(path)
    except ImageReadError as exc:
        raise MaterialError(_one_line(exc.reason), file=path) from None


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
        raise MaterialError(f"{int(np.isnan(values).sum())} values are NaN", file=path)
    outside = int(np.count_nonzero((values < 0.0) | (values > 1.0)))
    if outside:
        notes.append(f"{path.name}: {outside} values outside [0, 1] clipped")
        return np.clip(values, 0.0, 1.0)
    return values


# Largest texture loaded unless the caller allows more: 8K, whose fit fits a 24 GB machine (the material's 8
# channels in float32 are 2 GiB, its reference mips and the fit's buffers a few times that). A small file may
# claim far more (a decompression bomb); `bcf compress --max-pixels` and BCF_MAX_TEXTURE_PIXELS change it.
MAX_TEXTURE_PIXELS = 8192 * 8192
# Image formats whose colour values are linear by convention (an albedo in them is not sRGB-encoded).
LINEAR_FORMATS = {"openexr": "OpenEXR", "hdr": "Radiance HDR", "pfm": "PFM"}  # OpenImageIO's name: ours
# The stated normal convention is doubted when the field it implies is at least this many times further from
# being a gradient (a height map's) than the other convention's. Real normal maps are never exact gradients:
# on the 21 reference materials, correctly labelled maps scored at most 1.15x, maps read with the wrong
# convention 0.9-3.6x, so the margin catches the clear cases (3 of 21) and raises no false alarm.
CURL_RATIO = 2.0
CURL_SIDE = 1024  # the check looks at the map box-filtered to at most this many texels a side


def _curl_energy(x: np.ndarray, y_down: np.ndarray) -> float:
    """Mean squared curl of the slope field (x, y_down): zero for the gradient of any height map."""
    return float(np.mean(((np.roll(x, -1, 0) - x) - (np.roll(y_down, -1, 1) - y_down)) ** 2))


def _flipped_convention_note(path: Path, xy: np.ndarray, convention: str) -> str | None:
    """A note when the normal map's green channel looks flipped for `convention`: a tangent-space normal map
    baked from a height map is that map's slope field, which is curl-free; read with the wrong sign of Y it is
    not. xy: (h, w, 2) stored values in [0, 1]."""
    h, w = xy.shape[:2]
    step = max(1, max(h, w) // CURL_SIDE)
    xy = xy[:h - h % step, :w - w % step].reshape(h // step, step, w // step, step, 2).mean(axis=(1, 3))
    n = xy.astype(np.float64) * 2.0 - 1.0
    nz = np.sqrt(np.clip(1.0 - n[..., 0] ** 2 - n[..., 1] ** 2, 0.04, None))  # z of a unit normal, kept >= 0.2
    slope_x, slope_down = -n[..., 0] / nz, n[..., 1] / nz  # OpenGL: +Y is up, image rows go down
    stated, other = _curl_energy(slope_x, slope_down), _curl_energy(slope_x, -slope_down)
    if convention == "directx":
        stated, other = other, stated
    if stated < CURL_RATIO * other or stated == 0.0:
        return None
    guess, given = ("DirectX (Y-)", "directx") if convention == "opengl" else ("OpenGL (Y+)", "opengl")
    return (f"{path.name}: this normal map looks like {guess}: read as {convention} it is {stated / other:.1f}x "
            f"further from the slopes of a height map; set the normal convention to {given} if so")


@dataclass(frozen=True)
class InspectedMaterial:
    """A material checked from its files' headers alone, no pixel decoded: everything its job record and its
    result's identity need (`source`: sizes, formats, hashes, the normal convention) and the notes the headers
    give. `decode_texture_set` turns it into the `TextureSet`."""

    source: MaterialSource
    paths: dict[Role, Path]
    notes: tuple[str, ...]


def inspect_texture_set(files: MaterialFiles, name: str | None = None,
                        max_pixels: int = MAX_TEXTURE_PIXELS) -> InspectedMaterial:
    """Validate the files of `files` from their headers, without decoding pixels: completeness, readable
    headers, channel counts per role, at most `max_pixels` per file, equal sizes, power-of-two sizes >= 64.
    Raises MaterialError naming the file. `name` defaults to the albedo file's stem."""
    check_complete(files, None)
    roles = files.roles()
    headers: dict[Role, tuple[Path, _Header]] = {}
    for role, path in roles.items():
        header = read_header(Path(path))
        _check_channels(role, Path(path), header.channels)
        _check_pixels(Path(path), header, max_pixels)
        headers[role] = (Path(path), header)
    width, height = _check_sizes(headers)

    notes: list[str] = list(files.notes)
    defaults = {} if "arm" in roles else {role: value for role, value in DEFAULTS.items() if role not in roles}
    notes += [f"no {role} map: using the constant {value:g}" for role, value in defaults.items()]
    convention = files.normal_convention
    if convention is None:
        convention = "opengl"
        notes.append(f"{roles['normal'].name}: normal map convention not known from its name; assuming OpenGL "
                     f"(Y+); set the normal convention to directx if it is DirectX (Y-)")
    albedo_path, albedo_header = headers["albedo"]
    if albedo_header.format in LINEAR_FORMATS:
        notes.append(f"{albedo_path.name}: albedo in {LINEAR_FORMATS[albedo_header.format]}, which is linear by "
                     "convention; bcf stores, trains on and scores the values as they are (it does not encode them "
                     "to sRGB), so the decoded albedo is linear too")
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
    return InspectedMaterial(source=source, paths={role: path for role, (path, _) in headers.items()},
                             notes=tuple(notes))


def decode_texture_set(material: InspectedMaterial) -> TextureSet:
    """Decode the pixels of an inspected material (truncated or corrupt data is a MaterialError naming the file),
    clip values outside [0, 1] with a note, fill missing AO / metalness with their constants, and note a normal
    map whose green channel looks flipped for the convention."""
    source = material.source
    notes: list[str] = list(material.notes)
    channels = np.empty((source.height, source.width, len(CHANNELS)), dtype=np.float32)
    for described in source.files:
        path = material.paths[described.role]
        used = _used_channels(described.role, path, _read_pixels(path), notes)
        if not described.bits.startswith("uint"):  # OIIO maps unsigned integers into [0, 1] already: skip the scan
            used = _clip(path, used, notes)
        role = described.role
        target = TEXTURES[role] if role in TEXTURES else slice(CHANNEL_OF[role], CHANNEL_OF[role] + 1)
        channels[..., target] = used
    for role, value in source.defaults.items():
        channels[..., CHANNEL_OF[role]] = value
    flipped = _flipped_convention_note(material.paths["normal"], channels[..., TEXTURES["normal"]],
                                       source.normal_convention)
    if flipped:
        notes.append(flipped)
    return TextureSet(channels=channels, source=source, notes=tuple(notes))


def load_texture_set(files: MaterialFiles, name: str | None = None,
                     max_pixels: int = MAX_TEXTURE_PIXELS) -> TextureSet:
    """Read and validate the files of `files` into a TextureSet: `inspect_texture_set` (headers, before any pixel
    is decoded), then `decode_texture_set`. Missing AO becomes 1 and missing metalness 0 (recorded in
    `source.defaults`, with a note)."""
    return decode_texture_set(inspect_texture_set(files, name, max_pixels))


def load_material(directory: Path | None, explicit: MaterialFiles | None = None,
                  max_pixels: int = MAX_TEXTURE_PIXELS) -> TextureSet:
    """`resolve_material` then `load_texture_set`; the material is named after `directory` when given."""
    files = resolve_material(None if directory is None else Path(directory), explicit or MaterialFiles())
    return load_texture_set(files, name=None if directory is None else Path(directory).resolve().name,
                            max_pixels=max_pixels)


