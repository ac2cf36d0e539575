"""`bcf preview`: the compressed material on a lit sphere, next to the original textures (thin layer over
bcf.core.preview).

Library errors (a bad export folder or source material, no headless OpenGL) become UserError: one
`bcf: error: ...` line and exit code 2.
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path
from typing import Callable

from bcf.material_cli import cli_message

COMMANDS = {
    "preview": "render a compressed material on a lit sphere (headless OpenGL) into a PNG, optionally beside "
               "the original textures",
}
# What provides headless OpenGL when it is missing: the error names the packages, not just the symptom.
GL_PACKAGES = ("EGL and Mesa (llvmpipe, with BC6H support) provide it; on Debian/Ubuntu: apt-get install libegl1 "
               "libgl1-mesa-dri libegl-mesa0")


def add_commands(commands: argparse._SubParsersAction, user_error: type[Exception],
                 positive_int: Callable[[str], int], non_negative_int: Callable[[str], int]) -> None:
    from bcf.engine.preview import DEFAULT_LIGHT, MAX_SIZE, MIN_SIZE  # no torch: --help stays instant

    p = commands.add_parser(
        "preview", help=COMMANDS["preview"], description=COMMANDS["preview"] + ".",
        epilog="The sphere samples the four BC6H feature textures through the generated GLSL decoder "
               "(bcf_decode_grad, trilinear filtering), lit by one directional light (GGX specular, Lambert "
               "diffuse, AO-scaled ambient), ACES tone-mapped. Rendering is headless (EGL; Mesa's llvmpipe "
               "without a GPU).")
    p.add_argument("folder", metavar="OUT", help="a folder written by 'bcf compress'")
    p.add_argument("-o", "--output", metavar="PNG", required=True, type=Path, help="image to write (.png)")
    p.add_argument("--source", metavar="MATERIAL_DIR", type=Path,
                   help="also render the original textures (the folder given to 'bcf compress') the same way")
    p.add_argument("--size", type=positive_int, default=512, metavar="N",
                   help=f"sphere panel size in pixels, {MIN_SIZE} to {MAX_SIZE} (default: 512)")
    p.add_argument("--light-azimuth", type=float, default=DEFAULT_LIGHT[0], metavar="DEG",
                   help="light direction around the view axis: 0 = from the camera, positive = from the right "
                        f"(default: {DEFAULT_LIGHT[0]:g})")
    p.add_argument("--light-elevation", type=float, default=DEFAULT_LIGHT[1], metavar="DEG",
                   help=f"light height above the horizon, -90 to 90 (default: {DEFAULT_LIGHT[1]:g})")
    p.set_defaults(handler=functools.partial(_preview, user_error=user_error))


def _preview(args: argparse.Namespace, user_error: type[Exception]) -> int:
    from bcf.engine.preview import MAX_SIZE, MIN_SIZE

    # The cheap checks first: bad arguments fail before torch and OpenGL load.
    output: Path = args.output
    if output.suffix.lower() != ".png":
        raise user_error(f"{output}: unsupported image extension {output.suffix or '(none)'!r}; use .png")
    if output.is_dir():
        raise user_error(f"{output}: is a directory")
    if not MIN_SIZE <= args.size <= MAX_SIZE:
        raise user_error(f"--size must be in [{MIN_SIZE}, {MAX_SIZE}], got {args.size}")
    if not -90.0 <= args.light_elevation <= 90.0:
        raise user_error(f"--light-elevation must be in [-90, 90], got {args.light_elevation:g}")

    from bcf.core.export import artifacts as export
    from bcf.engine import gl
    from bcf.engine import preview
    from bcf.core.material.roles import MaterialError

    try:
        images = preview.render_preview(Path(args.folder), args.source, args.size,
                                        (args.light_azimuth, args.light_elevation))
    except (export.ExportError, MaterialError) as exc:
        raise user_error(cli_message(exc)) from None
    except gl.GLUnavailable as exc:
        message = str(exc)
        if "apt-get" not in message:
            message += f"; {GL_PACKAGES}"
        raise user_error(f"headless OpenGL is unavailable: {message}") from None
    for note in images.notes:
        print(f"note: {note}", flush=True)
    preview.write_preview(images, output)
    print(f"wrote {output}", flush=True)
    return 0
