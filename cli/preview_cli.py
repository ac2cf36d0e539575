"""`bcf preview`: the compressed material on a lit sphere, next to the original textures (thin layer over
bcf.engine.preview)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

from cyclopts import Parameter
from cyclopts.types import PositiveInt

from bcf.cli import Output, check_output_file, say
from bcf.core import InputError
from bcf.engine.preview import DEFAULT_LIGHT, MAX_SIZE, MIN_SIZE  # no torch: --help stays instant

# What provides headless OpenGL when it is missing: the error names the packages, not just the symptom.
GL_PACKAGES = ("EGL and Mesa (llvmpipe, with BC6H support) provide it; on Debian/Ubuntu: apt-get install libegl1 "
               "libgl1-mesa-dri libegl-mesa0")


def preview(folder: Path, /, *, output: Output, source: Optional[Path] = None, size: Annotated[PositiveInt, Parameter(help=f"sphere panel size in pixels, {MIN_SIZE} to {MAX_SIZE}")] = 512,
            light_azimuth: float = DEFAULT_LIGHT[0], light_elevation: float = DEFAULT_LIGHT[1]) -> int:
    """Render a compressed material on a lit sphere (headless OpenGL) into a PNG, optionally beside the
    original textures.

    The sphere samples the four BC6H feature textures through the generated GLSL decoder (bcf_decode_grad,
    trilinear filtering), lit by one directional light (GGX specular, Lambert diffuse, AO-scaled ambient),
    ACES tone-mapped. Rendering is headless (EGL; Mesa's llvmpipe without a GPU).

    Args:
        folder: a folder written by 'bcf compress'
        output: image to write (.png)
        source: also render the original textures (the folder given to 'bcf compress') the same way
        light_azimuth: light direction around the view axis in degrees: 0 = from the camera, positive = from
            the right
        light_elevation: light height above the horizon in degrees, -90 to 90
    """
    # The cheap checks first: bad arguments fail before torch and OpenGL load.
    check_output_file(output, (".png",), "image")
    if not MIN_SIZE <= size <= MAX_SIZE:
        raise InputError(f"--size must be in [{MIN_SIZE}, {MAX_SIZE}], got {size}")
    if not -90.0 <= light_elevation <= 90.0:
        raise InputError(f"--light-elevation must be in [-90, 90], got {light_elevation:g}")

    from bcf.engine.gl import GLUnavailable
    from bcf.engine.preview import render_preview, write_preview

    try:
        images = render_preview(folder, source, size, (light_azimuth, light_elevation))
    except GLUnavailable as exc:
        message = str(exc) if "apt-get" in str(exc) else f"{exc}; {GL_PACKAGES}"
        raise InputError(f"headless OpenGL is unavailable: {message}") from None
    for note in images.notes:
        say(f"note: {note}")
    write_preview(images, output)
    say(f"wrote {output}")
    return 0


COMMANDS = (preview,)
