"""Two independent BC6H decoders for the tests: OpenImageIO's DDS reader and Mesa's llvmpipe OpenGL driver.

Neither shares decoding code with `bcf`: OIIO decodes the DDS files we write (so it also checks our DDS layout),
and Mesa decodes the block arrays of a `BC6HTexture` uploaded with glCompressedTexImage2D (through bcf.core.gl,
which only hands the bytes over). Both return, for each level,
an (h_i, w_i, 3) float16 array; compare them through `.view(np.uint16)` to be bit exact (NaN != NaN otherwise).

Mesa runs headless through EGL (packages libegl1, libgl1-mesa-dri, libegl-mesa0). A `MesaBC6HDecoder` owns one
GL context; tests share one through a session fixture, while `decode_with_mesa(texture)` alone makes a
throwaway one.
"""

from __future__ import annotations

from os import PathLike
from typing import Any, Union

import numpy as np

from bcf.core.codec.containers import BC6HTexture

StrPath = Union[str, PathLike]



# ------------------------------------------------------------------------------------------- OpenImageIO


def _open_oiio(path: StrPath) -> Any:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RuntimeError(f"OpenImageIO cannot open {path}: {oiio.geterror()}")
    return inp


def decode_with_oiio(path: StrPath, level: int) -> np.ndarray:
    """Mip `level` of the DDS file at `path` as (h, w, 3) float16, decoded by OpenImageIO.

    read_image's second argument is the mip level (seek_subimage(0, m) then read_image(0, 0, ...) would read
    level 0 again).
    """
    inp = _open_oiio(path)
    try:
        if not inp.seek_subimage(0, level):
            raise RuntimeError(f"OpenImageIO finds no mip level {level} in {path}: {inp.geterror()}")
        spec = inp.spec()
        pixels = inp.read_image(0, level, 0, 3, "half")
        if pixels is None:
            raise RuntimeError(f"OpenImageIO cannot read level {level} of {path}: {inp.geterror()}")
    finally:
        inp.close()
    expected = (spec.height, spec.width, 3)
    if pixels.shape != expected or pixels.dtype != np.float16:
        raise RuntimeError(f"OpenImageIO gave {pixels.dtype} {pixels.shape} for level {level}, expected {expected}")
    return pixels


def oiio_mip_sizes(path: StrPath) -> list[tuple[int, int]]:
    """(width, height) of every mip level OpenImageIO finds in `path`, level 0 first."""
    inp = _open_oiio(path)
    try:
        sizes = []
        while inp.seek_subimage(0, len(sizes)):
            spec = inp.spec()
            sizes.append((spec.width, spec.height))
        return sizes
    finally:
        inp.close()


# ---------------------------------------------------------------------------------------------- Mesa GL


class MesaUnavailable(RuntimeError):
    """Mesa's llvmpipe with BPTC support cannot be reached through EGL."""


class MesaBC6HDecoder:
    """One headless Mesa llvmpipe context that decodes BC6H textures; `close()` releases it.

    The context and the upload come from `bcf.core.gl` (plain glCompressedTexImage2D of the block arrays);
    the decoding, and the texels read back, are Mesa's."""

    def __init__(self) -> None:
        from bcf.engine.gl import GLUnavailable, HeadlessGL

        try:
            self._gl: Any = HeadlessGL()
        except GLUnavailable as exc:
            raise MesaUnavailable(str(exc)) from exc
        renderer = self._gl.renderer
        if "llvmpipe" not in renderer:
            self.close()
            raise MesaUnavailable(f"EGL gives renderer {renderer!r}, not Mesa's llvmpipe")
        self.renderer: str = renderer

    def close(self) -> None:
        if self._gl is not None:
            self._gl.close()
            self._gl = None

    def __enter__(self) -> MesaBC6HDecoder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def decode(self, texture: BC6HTexture) -> list[np.ndarray]:
        """Every level of `texture` as (h_i, w_i, 3) float16, decoded by the GL driver."""
        if self._gl is None:
            raise RuntimeError("MesaBC6HDecoder is closed")
        uploaded = self._gl.bc6h_texture(texture)
        try:
            return [self._gl.read_texture_level(uploaded, level, texture.level_size(level))
                    for level in range(len(texture.levels))]
        finally:
            with self._gl.ctx:
                self._gl.gl.glDeleteTextures([uploaded.glo])


def mesa_unavailable_reason() -> str | None:
    """Why Mesa's llvmpipe with BPTC cannot be used here, or None when it can."""
    try:
        MesaBC6HDecoder().close()
    except MesaUnavailable as exc:
        return str(exc)
    return None


def mesa_available() -> bool:
    """True when a headless Mesa llvmpipe context with BPTC can be created."""
    return mesa_unavailable_reason() is None


def decode_with_mesa(texture: BC6HTexture, decoder: MesaBC6HDecoder | None = None) -> list[np.ndarray]:
    """Every level of `texture` as (h_i, w_i, 3) float16 via Mesa; pass `decoder` to reuse its context."""
    if decoder is not None:
        return decoder.decode(texture)
    with MesaBC6HDecoder() as own:
        return own.decode(texture)
