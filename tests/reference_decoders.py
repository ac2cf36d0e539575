"""Two independent BC6H decoders for the tests: OpenImageIO's DDS reader and Mesa's llvmpipe OpenGL driver.

Neither shares code with `bcf`: OIIO decodes the DDS files we write (so it also checks our DDS layout), and Mesa
decodes the block arrays of a `BC6HTexture` uploaded with glCompressedTexImage2D. Both return, for each level,
an (h_i, w_i, 3) float16 array; compare them through `.view(np.uint16)` to be bit exact (NaN != NaN otherwise).

Mesa runs headless through EGL (packages libegl1, libgl1-mesa-dri, libegl-mesa0). A `MesaBC6HDecoder` owns one
GL context; tests share one through a session fixture, while `decode_with_mesa(texture)` alone makes a
throwaway one.
"""

from __future__ import annotations

import ctypes
import os
import sys
from os import PathLike
from typing import Any, Union

import numpy as np

from bcf.core.containers import BC6HTexture

StrPath = Union[str, PathLike]

GL_COMPRESSED_RGB_BPTC_SIGNED_FLOAT = 0x8E8E
GL_COMPRESSED_RGB_BPTC_UNSIGNED_FLOAT = 0x8E8F
BPTC_EXTENSION = "GL_ARB_texture_compression_bptc"


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


def _import_gl_for_egl() -> Any:
    """Import PyOpenGL bound to EGL; PYOPENGL_PLATFORM only counts before the first OpenGL import."""
    if "OpenGL" not in sys.modules:
        os.environ["PYOPENGL_PLATFORM"] = "egl"
    import OpenGL.platform
    from OpenGL import GL

    platform = type(OpenGL.platform.PLATFORM).__name__
    if platform != "EGLPlatform":
        raise MesaUnavailable(f"PyOpenGL was already imported for {platform}, not EGL; set PYOPENGL_PLATFORM=egl")
    return GL


class MesaBC6HDecoder:
    """One headless Mesa llvmpipe context that decodes BC6H textures; `close()` releases it."""

    def __init__(self) -> None:
        self._ctx = None
        try:
            gl = _import_gl_for_egl()
            import moderngl
        except ImportError as exc:
            raise MesaUnavailable(f"moderngl and PyOpenGL are needed (pip install -e '.[dev]'): {exc}") from exc
        try:
            self._ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as exc:  # moderngl raises plain Exception when EGL or the driver is missing
            raise MesaUnavailable(f"cannot create a headless EGL context: {exc}") from exc
        self._gl = gl
        renderer = self._ctx.info.get("GL_RENDERER", "")
        if "llvmpipe" not in renderer:
            self.close()
            raise MesaUnavailable(f"EGL gives renderer {renderer!r}, not Mesa's llvmpipe")
        if BPTC_EXTENSION not in self._ctx.extensions:
            self.close()
            raise MesaUnavailable(f"{renderer} lacks {BPTC_EXTENSION}")
        self.renderer: str = renderer

    def close(self) -> None:
        if self._ctx is not None:
            self._ctx.release()
            self._ctx = None

    def __enter__(self) -> MesaBC6HDecoder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def decode(self, texture: BC6HTexture) -> list[np.ndarray]:
        """Every level of `texture` as (h_i, w_i, 3) float16, decoded by the GL driver."""
        if self._ctx is None:
            raise RuntimeError("MesaBC6HDecoder is closed")
        gl = self._gl
        with self._ctx:  # make our context current for the PyOpenGL calls
            name = gl.glGenTextures(1)
            try:
                gl.glBindTexture(gl.GL_TEXTURE_2D, name)
                self._upload(texture)
                return [self._read_level(texture, level) for level in range(len(texture.levels))]
            finally:
                gl.glDeleteTextures([name])

    def _upload(self, texture: BC6HTexture) -> None:
        gl = self._gl
        internal = GL_COMPRESSED_RGB_BPTC_SIGNED_FLOAT if texture.signed else GL_COMPRESSED_RGB_BPTC_UNSIGNED_FLOAT
        for level, blocks in enumerate(texture.levels):
            w, h = texture.level_size(level)
            data = np.ascontiguousarray(blocks, dtype=np.uint8).reshape(-1)
            gl.glCompressedTexImage2D(gl.GL_TEXTURE_2D, level, internal, w, h, 0, data)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_BASE_LEVEL, 0)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAX_LEVEL, len(texture.levels) - 1)

    def _read_level(self, texture: BC6HTexture, level: int) -> np.ndarray:
        gl = self._gl
        w, h = texture.level_size(level)
        got = tuple(gl.glGetTexLevelParameteriv(gl.GL_TEXTURE_2D, level, p) for p in (gl.GL_TEXTURE_WIDTH,
                                                                                     gl.GL_TEXTURE_HEIGHT))
        if got != (w, h):
            raise RuntimeError(f"GL reports level {level} as {got[0]}x{got[1]}, uploaded {w}x{h}")
        out = np.empty((h, w, 3), dtype=np.uint16)
        gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)  # RGB half rows are 6*w bytes, not 4-aligned
        gl.glGetTexImage(gl.GL_TEXTURE_2D, level, gl.GL_RGB, gl.GL_HALF_FLOAT, out.ctypes.data_as(ctypes.c_void_p))
        return out.view(np.float16)


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
