"""Texture-level BC6H tools built on the block codec (`bc6h`) and the containers (`containers`).

What the command line and the benchmarks need beyond single blocks: preparing an image for the format's
value range, encoding a whole mip chain, checking a written texture against its sources, and counting the
block modes a texture uses. Kept apart from `bc6h` (the codec knows nothing about files or mip chains) and
from `images` (which knows nothing about BC6H).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import numpy as np

from bcf.core.codec import bc6h, containers, partition
from bcf.core.codec.containers import BC6HTexture
from bcf.core.psnr import psnr_from_mse

__all__ = [
    "HALF_MAX",
    "LevelCheck",
    "container_kind",
    "encode_mips",
    "format_name",
    "mode_histogram",
    "encoder_modes",
    "psnr",
    "to_bc6h_range",
    "verify_texture",
]

StrPath = Union[str, PathLike]
HALF_MAX = 65504.0  # largest finite half float: BC6H cannot store anything larger
ALL_MODES = tuple(spec.number for spec in bc6h.MODES)


# ------------------------------------------------------------------------------------------ input range


def to_bc6h_range(image: np.ndarray, signed: bool) -> tuple[np.ndarray, list[str]]:
    """Clamp an image to what BC6H can hold, saying what was changed.

    image: any shape, float. Returns (a float32 copy clamped to [0, 65504] for UF16 or [-65504, 65504] for
    SF16 with NaN replaced by 0, and one human-readable message per kind of change, empty if none).
    The encoder would clamp the same way silently; doing it up front lets the caller warn and lets mips
    and verification see exactly the values that get encoded.
    """
    image = np.asarray(image, dtype=np.float32)
    low = -HALF_MAX if signed else 0.0
    problems: list[str] = []
    nan = int(np.isnan(image).sum())
    if nan:
        problems.append(f"{nan} NaN values replaced by 0")
    below = int((image < low).sum())
    if below:
        what = "negative values clamped to 0 (unsigned BC6H_UF16; use --signed to keep them)" if not signed \
            else f"values below {-HALF_MAX:g} clamped"
        problems.append(f"{below} {what}; minimum was {float(np.nanmin(image)):g}")
    above = int((image > HALF_MAX).sum())
    if above:
        problems.append(f"{above} values above {HALF_MAX:g} (the largest half float) clamped")
    clamped = np.clip(np.nan_to_num(image, nan=0.0, posinf=HALF_MAX, neginf=low), low, HALF_MAX)
    return clamped.astype(np.float32), problems


# --------------------------------------------------------------------------------------------- encoding


def encoder_modes(mode: int | str) -> tuple[int, ...]:
    """The candidate modes of the encoder for a user's choice: one mode number (1..14), or "auto" for every
    mode, each block taking the best."""
    if mode == "auto":
        return ALL_MODES
    bc6h.mode_spec(int(mode))  # raises ValueError for anything but 1..14
    return (int(mode),)


def encode_mips(mips: Sequence[np.ndarray], modes: Sequence[int], signed: bool,
                on_level: Optional[Callable[[int, np.ndarray, float], None]] = None) -> BC6HTexture:
    """Encode a mip chain (level 0 first, each (h_i, w_i, 3), sizes as `containers.mip_size`) to a texture.

    Every block takes the best of `modes` (`partition.fit_blocks`). `on_level(level, blocks, seconds)` is
    called after each level so a caller can report progress; blocks has shape (ceil(h_i / 4), ceil(w_i / 4), 16).
    """
    levels = []
    for i, level in enumerate(mips):
        start = time.perf_counter()
        blocks = partition.encode_image(level, modes, signed=signed)
        if on_level is not None:
            on_level(i, blocks, time.perf_counter() - start)
        levels.append(blocks)
    height, width = mips[0].shape[:2]
    return BC6HTexture(width, height, signed, tuple(levels))


# ------------------------------------------------------------------------------------------ verification


@dataclass(frozen=True)
class LevelCheck:
    """Round-trip quality of one mip level: decoded texture against its source level."""

    level: int
    width: int
    height: int
    psnr_db: float  # MAX_PSNR_DB when the decode is exact
    max_abs_error: float


def psnr(reference: np.ndarray, decoded: np.ndarray) -> float:
    """PSNR in dB of `decoded` against `reference` (same shape), peak = max(1, max of reference).

    A peak of at least 1 keeps LDR images on the usual [0, 1] scale while HDR images are judged against
    their own brightest value. Identical arrays score `MAX_PSNR_DB`.
    """
    reference = np.asarray(reference, dtype=np.float64)
    decoded = np.asarray(decoded, dtype=np.float64)
    if reference.shape != decoded.shape:
        raise ValueError(f"psnr needs equal shapes, got {reference.shape} and {decoded.shape}")
    mse = float(np.mean((decoded - reference) ** 2))
    peak = max(1.0, float(reference.max()))
    return psnr_from_mse(mse, peak)


def verify_texture(texture: BC6HTexture, sources: Sequence[np.ndarray]) -> list[LevelCheck]:
    """Decode every level of `texture` and compare it with `sources[level]` ((h_i, w_i, 3) each).

    Raises ValueError if the texture and the sources disagree on level count or sizes.
    """
    if len(sources) != len(texture.levels):
        raise ValueError(f"texture has {len(texture.levels)} levels but {len(sources)} sources were given")
    checks = []
    for i, (blocks, source) in enumerate(zip(texture.levels, sources)):
        width, height = texture.level_size(i)
        if source.shape[:2] != (height, width):
            raise ValueError(f"level {i} is {width}x{height} but its source is {source.shape[1]}x{source.shape[0]}")
        decoded = bc6h.decode_image(blocks, width, height, texture.signed).astype(np.float64)
        error = float(np.abs(decoded - source).max())
        checks.append(LevelCheck(i, width, height, psnr(source, decoded), error))
    return checks


# ----------------------------------------------------------------------------------------------- inspect


def _mode_lookup() -> np.ndarray:
    """(32,) mode number (1..14) of each 5-bit mode code, 0 for the reserved codes."""
    table = np.zeros(32, dtype=np.int64)
    for spec in bc6h.MODES:
        table[spec.code] = spec.number
    return table


def mode_histogram(blocks: np.ndarray) -> dict[Union[int, str], int]:
    """Count the BC6H modes of `blocks` ((..., 16) uint8).

    Returns {mode number: count} for the modes that occur, ascending, then "reserved": count if any block
    uses a reserved code. The code is read as `bc6h.decode_blocks` reads it: the low 2 bits of byte 0 if
    they are 0 or 1 (modes 1 and 2), else its low 5 bits.
    """
    blocks = np.asarray(blocks)
    if blocks.dtype != np.uint8 or blocks.shape[-1:] != (bc6h.BLOCK_BYTES,):
        raise ValueError(f"blocks must be uint8 of shape (..., 16), got {blocks.dtype} {blocks.shape}")
    first = blocks.reshape(-1, bc6h.BLOCK_BYTES)[:, 0]
    low2 = first & 0b11
    code = np.where(low2 < 2, low2, first & 0b11111)
    counts = np.bincount(_mode_lookup()[code], minlength=15)  # index 0 collects the reserved codes
    histogram: dict[Union[int, str], int] = {mode: int(counts[mode]) for mode in range(1, 15) if counts[mode]}
    if counts[0]:
        histogram["reserved"] = int(counts[0])
    return histogram


def container_kind(path: StrPath) -> str:
    """"DDS" or "KTX2" from the file's magic bytes (as `containers.read_texture` decides), else "unknown"."""
    with Path(path).open("rb") as file:
        head = file.read(len(containers.KTX2_IDENTIFIER))
    if head.startswith(containers.DDS_MAGIC):
        return "DDS"
    if head.startswith(containers.KTX2_IDENTIFIER):
        return "KTX2"
    return "unknown"


def format_name(signed: bool) -> str:
    """The DXGI-style name of the texture format."""
    return "BC6H_SF16" if signed else "BC6H_UF16"
