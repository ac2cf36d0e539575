"""The `bcf` command line: a thin layer over `bcf.core` (argument parsing, messages, exit codes).

Exit codes: 0 success, 2 user error (bad arguments, missing or unreadable input, malformed container, an
output that cannot be written), 130 interrupted. User errors print one line `bcf: error: ...` on stderr.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, NoReturn, Optional, Sequence

from bcf import __version__
from bcf import batch_cli, material_cli, preview_cli, service_cli
from bcf.core.codec import containers
from bcf.core.errors import InputError
from bcf.core.material import images

if TYPE_CHECKING:
    import numpy as np

# `bcf.core.bc6h` imports torch (about 1.5 s), so the commands import it when they run; `--help`,
# `--version` and argument errors stay instant. `images` and `containers` only need numpy and OIIO.

CONTAINER_WRITERS = {".dds": "DDS", ".ktx2": "KTX2"}

# (command words, one-line description): shown in `bcf --help` and used as each sub-command's help.
COMMANDS = {
    "encode": "compress an image (EXR, PNG, JPEG, ...) to a mipmapped BC6H texture (.dds or .ktx2)",
    "decode": "decode one mip level of a BC6H texture to an image (.exr or .png)",
    "info": "describe a BC6H texture: container, format, levels and the block modes of level 0",
}


class UserError(Exception):
    """A problem with the user's input or arguments: reported as `bcf: error: <message>`, exit code 2."""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose errors become UserError, so they get the same one-line format as every other error."""

    def error(self, message: str) -> NoReturn:
        raise UserError(f"{message} (see '{self.prog} --help')")


# ------------------------------------------------------------------------------------------------ parser


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The full `bcf` argument parser; each leaf command stores its handler in `handler`."""
    epilog = "bc6h commands:\n" + "\n".join(f"  bc6h {name:<8} {text}" for name, text in COMMANDS.items())
    parser = _Parser(prog="bcf", description="Neural block-compressed features (BC6H) for PBR materials.",
                     epilog=epilog, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"bcf {__version__}")
    groups = parser.add_subparsers(title="commands", metavar="COMMAND", dest="group", required=True)
    material_cli.add_commands(groups, UserError, _positive_int, _non_negative_int)
    batch_cli.add_commands(groups, UserError, _positive_int, _non_negative_int)
    service_cli.add_commands(groups, UserError, _positive_int, _non_negative_int)
    preview_cli.add_commands(groups, UserError, _positive_int, _non_negative_int)
    bc6h = groups.add_parser("bc6h", help="BC6H textures: encode, decode, info",
                             description="BC6H (HDR, 3 channels, 8 bits per texel) textures in DDS or KTX2.")
    commands = bc6h.add_subparsers(title="commands", metavar="COMMAND", dest="command", required=True)
    _add_encode(commands)
    _add_decode(commands)
    _add_info(commands)
    return parser


def _add_encode(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser("encode", help=COMMANDS["encode"], description=COMMANDS["encode"] + ".")
    p.add_argument("image", metavar="IMAGE", help="input image; channels as stored, no colour conversion")
    p.add_argument("-o", "--output", metavar="OUT", required=True, help="output texture: .dds or .ktx2")
    p.add_argument("--mode", type=int, choices=(10, 11), default=10,
                   help="BC6H mode: 10 = two regions, 6-bit endpoints, 3-bit indices; "
                        "11 = one region, 10-bit endpoints, 4-bit indices (default: 10)")
    p.add_argument("--signed", action="store_true", help="BC6H_SF16 (keeps negative values); default BC6H_UF16")
    mips = p.add_mutually_exclusive_group()
    mips.add_argument("--levels", type=_positive_int, metavar="N", help="number of mip levels (default: all)")
    mips.add_argument("--no-mips", action="store_true", help="level 0 only")
    p.add_argument("--verify", action="store_true",
                   help="read the file back, decode every level and print PSNR and max error per level")
    p.set_defaults(handler=_encode)


def _add_decode(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser("decode", help=COMMANDS["decode"], description=COMMANDS["decode"] + ".")
    p.add_argument("file", metavar="FILE", help="BC6H texture (.dds or .ktx2, detected by content)")
    p.add_argument("-o", "--output", metavar="OUT", required=True,
                   help=".exr (half float, exact) or .png (16-bit, clamped to [0, 1])")
    p.add_argument("--level", type=_non_negative_int, default=0, metavar="N", help="mip level (default: 0)")
    p.set_defaults(handler=_decode)


def _add_info(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser("info", help=COMMANDS["info"], description=COMMANDS["info"] + ".")
    p.add_argument("file", metavar="FILE", help="BC6H texture (.dds or .ktx2, detected by content)")
    p.set_defaults(handler=_info)


# ---------------------------------------------------------------------------------------------- helpers


def _warn(message: str) -> None:
    print(f"bcf: warning: {message}", file=sys.stderr)


def _say(message: str) -> None:
    print(message, flush=True)  # flush: progress should show while the next level is being encoded


def _check_output(path: Path, allowed: Sequence[str], what: str) -> str:
    """Fail early (before any work) on an output path that cannot be right; returns its lower-case suffix."""
    suffix = path.suffix.lower()
    if suffix not in allowed:
        raise UserError(f"{path}: unsupported {what} extension {suffix or '(none)'!r}; use {' or '.join(allowed)}")
    if path.is_dir():
        raise UserError(f"{path}: is a directory")
    return suffix


@contextmanager
def _atomic_output(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; move it onto `path` only if the block succeeds.

    A failed or interrupted write then never leaves a partial file under the requested name. The temporary
    name keeps the suffix because OpenImageIO picks the image format by extension.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def _size(width: int, height: int) -> str:
    return f"{width}x{height}"


def _levels(count: int) -> str:
    return f"{count} level" + ("s" if count != 1 else "")


def _read_texture(path: str) -> containers.BC6HTexture:
    if not Path(path).exists():
        raise UserError(f"{path}: no such file")
    if not Path(path).is_file():
        raise UserError(f"{path}: not a regular file")
    return containers.read_texture(path)


def _level_table(texture: containers.BC6HTexture) -> list[str]:
    lines = [f"  {'level':>5}  {'size':>11}  {'blocks':>8}  {'bytes':>10}"]
    for i, blocks in enumerate(texture.levels):
        lines.append(f"  {i:>5}  {_size(*texture.level_size(i)):>11}  {blocks.shape[0] * blocks.shape[1]:>8}"
                     f"  {blocks.nbytes:>10}")
    return lines


# --------------------------------------------------------------------------------------------- commands


def _encode(args: argparse.Namespace) -> int:
    output = Path(args.output)
    container = CONTAINER_WRITERS[_check_output(output, tuple(CONTAINER_WRITERS), "texture")]
    source = images.read_rgb(args.image)
    height, width = source.shape[:2]
    full = containers.full_mip_count(width, height)
    count = 1 if args.no_mips else (args.levels or full)
    if count > full:
        raise UserError(f"--levels {count}: {args.image} is {_size(width, height)}, which has at most {full} "
                        "mip levels")
    from bcf.core.codec import textures as bc6h_tools  # after the cheap checks: bad input fails without loading torch

    image, problems = bc6h_tools.to_bc6h_range(source, args.signed)
    for problem in problems:
        _warn(f"{args.image}: {problem}")
    fmt = bc6h_tools.format_name(args.signed)
    _say(f"encoding {args.image} ({_size(width, height)}) as {fmt} mode {args.mode}, {_levels(count)}")
    start = time.perf_counter()
    mips = images.mip_chain(image, count)

    def progress(level: int, blocks: "np.ndarray", seconds: float) -> None:
        h, w = mips[level].shape[:2]
        _say(f"  level {level}: {_size(w, h):>11}  {blocks.shape[0] * blocks.shape[1]:>7} blocks  {seconds:6.2f} s")

    texture = bc6h_tools.encode_mips(mips, args.mode, args.signed, on_level=progress)
    writer = containers.write_dds if container == "DDS" else containers.write_ktx2
    with _atomic_output(output) as temporary:
        writer(temporary, texture)
    elapsed = time.perf_counter() - start
    data = sum(level.nbytes for level in texture.levels)
    _say(f"wrote {output}: {container} {fmt}, {_size(width, height)}, {_levels(count)}, mode {args.mode}, "
         f"{output.stat().st_size} bytes ({data} of blocks), {elapsed:.2f} s")
    if args.verify:
        _print_verification(output, mips)
    return 0


def _print_verification(path: Path, mips: Sequence["np.ndarray"]) -> None:
    """Read `path` back and print the per-level quality against the encoder's input mips."""
    from bcf.core.codec import textures as bc6h_tools

    checks = bc6h_tools.verify_texture(containers.read_texture(path), mips)
    _say(f"verify {path} (decoded vs. source mip; PSNR peak = max(1, source max)):")
    _say(f"  {'level':>5}  {'size':>11}  {'PSNR (dB)':>9}  {'max abs err':>11}")
    for check in checks:
        _say(f"  {check.level:>5}  {_size(check.width, check.height):>11}  {check.psnr_db:>9.2f}"
             f"  {check.max_abs_error:>11.4g}")


def _decode(args: argparse.Namespace) -> int:
    output = Path(args.output)
    suffix = _check_output(output, tuple(images.WRITE_EXTENSIONS), "image")
    texture = _read_texture(args.file)
    if args.level >= len(texture.levels):
        raise UserError(f"{args.file}: --level {args.level} does not exist; the file has levels "
                        f"0..{len(texture.levels) - 1}")
    from bcf.core.codec import bc6h

    width, height = texture.level_size(args.level)
    decoded = bc6h.decode_image(texture.levels[args.level], width, height, texture.signed)
    if suffix == ".png" and (decoded.min() < 0 or decoded.max() > 1):
        _warn(f"{output}: PNG holds [0, 1]; values in [{float(decoded.min()):g}, {float(decoded.max()):g}] "
              "are clamped (use .exr to keep them)")
    with _atomic_output(output) as temporary:
        images.write_rgb(temporary, decoded)
    _say(f"wrote {output}: level {args.level} ({_size(width, height)}) of {args.file}")
    return 0


def _info(args: argparse.Namespace) -> int:
    texture = _read_texture(args.file)
    from bcf.core.codec import textures as bc6h_tools  # after the cheap checks: bad input fails without loading torch

    histogram = bc6h_tools.mode_histogram(texture.levels[0])
    total = sum(histogram.values())
    lines = [
        f"file:      {args.file} ({Path(args.file).stat().st_size} bytes)",
        f"container: {bc6h_tools.container_kind(args.file)}",
        f"format:    {bc6h_tools.format_name(texture.signed)}",
        f"size:      {_size(texture.width, texture.height)}",
        f"levels:    {len(texture.levels)}",
        *_level_table(texture),
        "level 0 block modes:",
    ]
    for mode, count in histogram.items():
        label = "reserved" if mode == "reserved" else f"mode {mode}"
        lines.append(f"  {label}: {count} blocks ({100.0 * count / total:.1f} %)")
    _say("\n".join(lines))
    return 0


# ------------------------------------------------------------------------------------------------- main


def _error_message(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    return str(exc)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run `bcf` with `argv` (default: sys.argv[1:]) and return the exit code."""
    # Errors the user can fix; anything else is a bug in bcf and keeps its traceback.
    user_errors: tuple[type[BaseException], ...] = (
        UserError, OSError, InputError)
    try:
        args = build_parser().parse_args(argv)
        handler: Callable[[argparse.Namespace], int] = args.handler
        return handler(args)
    except SystemExit as exc:  # --help and --version end through parser.exit()
        return exc.code if isinstance(exc.code, int) else 0
    except user_errors as exc:
        print(f"bcf: error: {material_cli.cli_message(exc) if isinstance(exc, InputError) else _error_message(exc)}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("bcf: interrupted", file=sys.stderr)
        return 130
