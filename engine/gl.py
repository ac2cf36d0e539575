"""Headless OpenGL for `bcf preview` and the renderer tests: a moderngl context through EGL (Mesa's llvmpipe
on machines without a GPU), BC6H textures uploaded as compressed textures, full-screen fragment passes read
back as float32.

PyOpenGL is used only for what moderngl lacks (compressed uploads, reading a texture level back); it must be
bound to EGL, which only works if this module imports it first (PYOPENGL_PLATFORM counts at the first import).
"""

from __future__ import annotations

import ctypes
import os
import sys
from typing import Any, Optional, Sequence

import numpy as np

from bcf.core import Address, BC6HTexture

__all__ = ["BPTC_EXTENSION", "GLUnavailable", "HeadlessGL"]

BPTC_EXTENSION = "GL_ARB_texture_compression_bptc"
GL_COMPRESSED_RGB_BPTC_SIGNED_FLOAT = 0x8E8E
GL_COMPRESSED_RGB_BPTC_UNSIGNED_FLOAT = 0x8E8F

_VERTEX = """#version 330 core
in vec2 position;
void main() { gl_Position = vec4(position, 0.0, 1.0); }
"""


class GLUnavailable(RuntimeError):
    """No headless OpenGL 3.3 context with BC6H (BPTC) support can be created here."""


def _import_gl_for_egl() -> Any:
    if "OpenGL" not in sys.modules:
        os.environ["PYOPENGL_PLATFORM"] = "egl"
    try:
        import OpenGL.platform
        from OpenGL import GL
    except ImportError as exc:
        raise GLUnavailable(f"PyOpenGL is needed: {exc}") from exc
    platform = type(OpenGL.platform.PLATFORM).__name__
    if platform != "EGLPlatform":
        raise GLUnavailable(f"PyOpenGL was already imported for {platform}, not EGL; set PYOPENGL_PLATFORM=egl")
    return GL


class HeadlessGL:
    """One headless context; `close()` (or `with`) releases it. Textures and programs live as long as it."""

    def __init__(self) -> None:
        self.ctx: Any = None
        gl = _import_gl_for_egl()
        try:
            import moderngl
        except ImportError as exc:
            raise GLUnavailable(f"moderngl is needed: {exc}") from exc
        try:
            self.ctx = moderngl.create_standalone_context(backend="egl", require=330)
        except Exception as exc:  # moderngl raises plain Exception when EGL or the driver is missing
            raise GLUnavailable(f"cannot create a headless EGL OpenGL 3.3 context: {exc} (on Debian: apt-get "
                                "install libegl1 libgl1-mesa-dri libegl-mesa0)") from exc
        self.gl = gl
        self.renderer: str = self.ctx.info.get("GL_RENDERER", "")
        if BPTC_EXTENSION not in self.ctx.extensions:
            self.close()
            raise GLUnavailable(f"{self.renderer} lacks {BPTC_EXTENSION} (BC6H textures)")
        quad = np.array([-1, -1, 3, -1, -1, 3], dtype="f4")  # one triangle covering the viewport
        with self.ctx:
            self._quad = self.ctx.buffer(quad.tobytes())

    def close(self) -> None:
        if self.ctx is not None:
            self.ctx.release()
            self.ctx = None

    def __enter__(self) -> "HeadlessGL":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -------------------------------------------------------------------------------------------- textures

    def _sampler_state(self, address: Address, levels: int) -> None:
        gl = self.gl
        wrap = gl.GL_REPEAT if address == "wrap" else gl.GL_CLAMP_TO_EDGE
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_BASE_LEVEL, 0)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAX_LEVEL, levels - 1)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MIN_FILTER, gl.GL_LINEAR_MIPMAP_LINEAR)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAG_FILTER, gl.GL_LINEAR)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_WRAP_S, wrap)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_WRAP_T, wrap)

    def bc6h_texture(self, texture: BC6HTexture, address: Address = "wrap") -> Any:
        """Upload every level of a BC6H texture as a compressed texture with trilinear filtering; returns a
        moderngl texture (row 0 of the blocks at t = 0, so t is bcf's v)."""
        gl = self.gl
        internal = GL_COMPRESSED_RGB_BPTC_SIGNED_FLOAT if texture.signed else GL_COMPRESSED_RGB_BPTC_UNSIGNED_FLOAT
        with self.ctx:
            name = gl.glGenTextures(1)
            gl.glBindTexture(gl.GL_TEXTURE_2D, name)
            for level, blocks in enumerate(texture.levels):
                w, h = texture.level_size(level)
                data = np.ascontiguousarray(blocks, dtype=np.uint8).reshape(-1)
                gl.glCompressedTexImage2D(gl.GL_TEXTURE_2D, level, internal, w, h, 0, data)
            self._sampler_state(address, len(texture.levels))
            return self.ctx.external_texture(int(name), (texture.width, texture.height), 3, 0, "f2")

    def read_texture_level(self, texture: Any, level: int, size: tuple[int, int]) -> np.ndarray:
        """Level `level` of a texture as the driver stores it: (h, w, 3) float16."""
        gl = self.gl
        w, h = size
        out = np.empty((h, w, 3), dtype=np.uint16)
        with self.ctx:
            gl.glBindTexture(gl.GL_TEXTURE_2D, texture.glo)
            got = tuple(gl.glGetTexLevelParameteriv(gl.GL_TEXTURE_2D, level, p)
                        for p in (gl.GL_TEXTURE_WIDTH, gl.GL_TEXTURE_HEIGHT))
            if got != (w, h):
                raise RuntimeError(f"GL reports level {level} as {got[0]}x{got[1]}, expected {w}x{h}")
            gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)  # RGB half rows are 6*w bytes, not 4-aligned
            gl.glGetTexImage(gl.GL_TEXTURE_2D, level, gl.GL_RGB, gl.GL_HALF_FLOAT,
                             out.ctypes.data_as(ctypes.c_void_p))
        return out.view(np.float16)

    def float_texture(self, image: np.ndarray, address: Address = "wrap") -> Any:
        """An (h, w, c) float image (c = 1..4) as a float32 texture, mipmapped by the driver (box filter)."""
        h, w, c = image.shape
        with self.ctx:
            texture = self.ctx.texture((w, h), c, np.ascontiguousarray(image, dtype="f4").tobytes(), dtype="f4")
            texture.repeat_x = texture.repeat_y = address == "wrap"
            texture.build_mipmaps()
        return texture

    # -------------------------------------------------------------------------------------------- drawing

    def render(self, fragment_shader: str, size: tuple[int, int], textures: Optional[dict[str, Any]] = None,
               uniforms: Optional[dict[str, Any]] = None, outputs: int = 1) -> list[np.ndarray]:
        """Run `fragment_shader` (with `#version`, writing `outputs` vec4 outputs at locations 0..) over a
        width x height viewport; returns each output as (h, w, 4) float32, row 0 = the bottom (y = 0) row."""
        w, h = size
        with self.ctx:  # current for this call only: other contexts (e.g. a test's) may exist in the process
            program = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=fragment_shader)
            try:
                for unit, (name, texture) in enumerate((textures or {}).items()):
                    if name in program:
                        program[name].value = unit
                    texture.use(location=unit)
                for name, value in (uniforms or {}).items():
                    if name in program:
                        program[name].value = value
                targets = [self.ctx.texture((w, h), 4, dtype="f4") for _ in range(outputs)]
                framebuffer = self.ctx.framebuffer(color_attachments=targets)
                vao = self.ctx.vertex_array(program, [(self._quad, "2f", "position")])
                framebuffer.use()
                self.ctx.viewport = (0, 0, w, h)
                framebuffer.clear(0.0, 0.0, 0.0, 0.0)
                vao.render(vertices=3)
                results = [np.frombuffer(framebuffer.read(components=4, attachment=i, dtype="f4"), dtype=np.float32)
                           .reshape(h, w, 4).copy() for i in range(outputs)]
                # Reading attachments past the first leaves a GL_INVALID_OPERATION in Mesa's error queue (moderngl
                # restoring the read buffer; the pixels are right, the tests compare them); drain it so the next
                # PyOpenGL call, which checks glGetError, is not blamed for it.
                while self.gl.glGetError() != self.gl.GL_NO_ERROR:
                    pass
                for item in (vao, framebuffer, *targets):
                    item.release()
                return results
            finally:
                program.release()

    def render_bc6h_material(self, source: str, size: tuple[int, int], textures: Sequence[Any],
                             uniforms: Optional[dict[str, Any]] = None, outputs: int = 1) -> list[np.ndarray]:
        """`render` with the four feature textures bound to bcf_T0..bcf_T3."""
        bound = {f"bcf_T{i}": t for i, t in enumerate(textures)}
        return self.render(source, size, bound, uniforms, outputs)
