"""Image files <-> float RGB arrays, and box-filtered mip chains.

Images are numpy arrays of shape (h, w, 3), float32, holding the values as stored in the file: 8- and
16-bit integer formats are normalised to [0, 1] by OpenImageIO, float formats are passed through. No
colour-space conversion happens anywhere here (an sRGB PNG stays sRGB-encoded).
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path
from typing import Literal, Union

import numpy as np
import OpenImageIO as oiio

from bcf.core.errors import InputError

__all__ = ["ImageReadError", "ImageWriteError", "WRITE_EXTENSIONS", "mip_chain", "read_image", "read_rgb", "write_rgb"]

StrPath = Union[str, PathLike]

# Extensions `write_rgb` understands, mapped to the pixel type it stores.
WRITE_EXTENSIONS = {".exr": "half", ".png": "uint16"}


class ImageReadError(InputError):
    """An image file that is missing or that OpenImageIO cannot read; the message names the file."""


class ImageWriteError(InputError):
    """An image that cannot be written (bad extension or an OpenImageIO failure); the message names the file."""


# ------------------------------------------------------------------------------------------------ read


def read_image(path: StrPath) -> np.ndarray:
    """Read the first subimage of `path` as (h, w, c) float32 with every stored channel, in file order.

    Alpha is returned unassociated (as stored), never premultiplied. Raises ImageReadError for a missing,
    unreadable, truncated or corrupt file.
    """
    file = Path(path)
    if not file.exists():
        raise ImageReadError("no such file", file=path)
    if not file.is_file():
        raise ImageReadError("not a regular file", file=path)
    # By default OIIO premultiplies colour by alpha for formats that store it unassociated (PNG, TIFF, ...);
    # ask for the channels untouched so RGBA and grey+alpha files give the stored values.
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    image_input = oiio.ImageInput.open(str(file), config)
    if image_input is None:
        raise ImageReadError(f"cannot read image: {oiio.geterror() or 'unknown OpenImageIO error'}", file=path)
    try:
        channels = image_input.spec().nchannels
        pixels = image_input.read_image(0, 0, 0, channels, "float")
        # OIIO returns partial data for e.g. truncated JPEGs and only flags the problem: treat it as fatal,
        # a silently grey bottom half is worse than an error.
        problem = image_input.geterror()
    finally:
        image_input.close()
    if pixels is None or problem:
        raise ImageReadError(f"cannot read image: {problem or 'unknown OpenImageIO error'}", file=path)
    return np.asarray(pixels, dtype=np.float32).reshape(*pixels.shape[:2], channels)


def read_rgb(path: StrPath) -> np.ndarray:
    """Read the first subimage of `path` as (h, w, 3) float32.

    1 channel is replicated to RGB (grey), 2 channels get a zero blue, 4+ channels keep the first three.
    Raises ImageReadError for a missing, unreadable, truncated or corrupt file.
    """
    return _to_rgb(read_image(path))


def _to_rgb(pixels: np.ndarray) -> np.ndarray:
    """(h, w, c) -> (h, w, 3) by the channel rules of `read_rgb`."""
    channels = pixels.shape[2]
    if channels == 1:
        return np.repeat(pixels, 3, axis=2)
    if channels == 2:
        return np.concatenate([pixels, np.zeros_like(pixels[..., :1])], axis=2)
    return np.ascontiguousarray(pixels[..., :3])


# ----------------------------------------------------------------------------------------------- write


def write_rgb(path: StrPath, image: np.ndarray, png_bits: Literal[8, 16] = 16) -> None:
    """Write an (h, w, 3) float image; the format follows the extension of `path`.

    .exr: half floats (values beyond the half range become +-inf, as a cast to half does).
    .png: `png_bits` (16 by default, 8 for compact samples) unsigned integers of the values clamped to
    [0, 1], rounded to nearest. Other extensions raise ImageWriteError (a ValueError).
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"{path}: write_rgb needs an (h, w, 3) image, got shape {image.shape}")
    suffix = Path(path).suffix.lower()
    if suffix not in WRITE_EXTENSIONS:
        raise ImageWriteError(f"unsupported image extension {suffix or '(none)'!r}; "
                              f"use one of {', '.join(WRITE_EXTENSIONS)}")
    if suffix == ".exr":
        with np.errstate(over="ignore"):  # overflow to +-inf is the documented behaviour, not a surprise
            pixels, pixel_type = image.astype(np.float16), "half"
    else:
        if png_bits not in (8, 16):
            raise ValueError(f"png_bits must be 8 or 16, got {png_bits}")
        # Quantise here rather than letting OIIO convert, so the rounding rule is ours and documented.
        top = (1 << png_bits) - 1
        dtype = np.uint8 if png_bits == 8 else np.uint16
        pixels = np.rint(np.clip(np.nan_to_num(image.astype(np.float64)), 0.0, 1.0) * top).astype(dtype)
        pixel_type = "uint8" if png_bits == 8 else "uint16"
    _write_pixels(path, np.ascontiguousarray(pixels), pixel_type)


def _write_pixels(path: StrPath, pixels: np.ndarray, pixel_type: str) -> None:
    height, width, channels = pixels.shape
    output = oiio.ImageOutput.create(str(path))
    if output is None:
        raise ImageWriteError(f"cannot write image: {oiio.geterror()}", file=path)
    if not output.open(str(path), oiio.ImageSpec(width, height, channels, pixel_type)):
        raise ImageWriteError(f"cannot write image: {output.geterror()}", file=path)
    ok = output.write_image(pixels)
    problem = output.geterror()
    closed = output.close()
    if not ok or not closed or problem:
        raise ImageWriteError(f"cannot write image: {problem or output.geterror() or 'write failed'}", file=path)


# ------------------------------------------------------------------------------------------------- mips


def mip_chain(image: np.ndarray, levels: int | None = None) -> list[np.ndarray]:
    """Mip levels of an (h, w, C) image by box filtering, level 0 (a float32 copy of `image`) first.

    Level i is max(1, w >> i) x max(1, h >> i), the sizes DDS/KTX2 expect; `levels=None` builds the full chain
    down to 1x1 (floor(log2(max(w, h))) + 1 levels), otherwise the first `levels` levels.

    Filter rule, applied separably to each side: a side of n texels becomes m = max(1, n // 2) texels, and
    output texel i is the average of the input over the interval [i * n / m, (i + 1) * n / m), each input
    texel weighted by how much of it the interval covers. For even n this is the plain 2x2 box average; for
    odd n each output texel covers 2 + 1/m input texels (e.g. 5 -> 2: weights 1, 1, 0.5 and 0.5, 1, 1, over
    2.5), so no texel is dropped and the image mean is preserved for every size; a side of 1 stays 1.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"mip_chain needs an (h, w, C) image with h, w >= 1, got shape {image.shape}")
    height, width = image.shape[:2]
    full = max(width, height).bit_length()  # floor(log2(max side)) + 1, exact for ints
    if levels is None:
        levels = full
    if not 1 <= levels <= full:
        raise ValueError(f"a {width}x{height} image has 1 to {full} mip levels, {levels} were asked for")
    chain = [image.astype(np.float32, copy=True)]
    for _ in range(levels - 1):
        chain.append(_halve(chain[-1]))
    return chain


def _halve(image: np.ndarray) -> np.ndarray:
    """One box-filter step of `mip_chain`: (h, w, C) -> (max(1, h // 2), max(1, w // 2), C) float32."""
    rows = _resample_axis(image.astype(np.float64), axis=0)
    return _resample_axis(rows, axis=1).astype(np.float32)


def _resample_axis(image: np.ndarray, axis: int) -> np.ndarray:
    """Apply the coverage-weighted box filter of `mip_chain` along `axis` (0 or 1)."""
    n = image.shape[axis]
    m = max(1, n // 2)
    if n == 2 * m:  # the common case: average neighbouring pairs with a reshape, no gather
        shape = image.shape[:axis] + (m, 2) + image.shape[axis + 1:]
        return image.reshape(shape).mean(axis=axis + 1)
    index, weight = _box_taps(n, m)  # (m, K) each
    taken = np.take(image, index, axis=axis)  # (..., m, K, ...) with the taps right after `axis`
    weight = weight.reshape((m, weight.shape[1]) + (1,) * (image.ndim - axis - 1))
    return (taken * weight).sum(axis=axis + 1)


def _box_taps(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Input texel indices (m, K) and weights (m, K) (rows sum to 1) of a box filter from n to m texels.

    Works in units of 1/m of a texel so every overlap is an exact integer: output i spans [i n, (i + 1) n),
    input j spans [j m, (j + 1) m).
    """
    taps = -(-n // m) + 1  # an interval of n/m texels touches at most ceil(n/m) + 1 of them
    first = (np.arange(m) * n) // m  # first input texel each output touches
    index = first[:, None] + np.arange(taps)[None, :]  # (m, K)
    start, end = np.arange(m)[:, None] * n, (np.arange(m)[:, None] + 1) * n
    overlap = np.clip(np.minimum(end, (index + 1) * m) - np.maximum(start, index * m), 0, None)
    # Taps past the last texel have zero overlap; clamp their index so the gather stays in bounds.
    return np.minimum(index, n - 1), overlap / n
