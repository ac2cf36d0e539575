"""`bcf bc6h encode|decode|info`: the BC6H codec on its own (thin layer over bcf.core)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, Optional, Sequence

from cyclopts import Parameter
from cyclopts.types import NonNegativeInt, PositiveInt

from bcf.cli import EXCLUSIVE, Output, check_output_file, say
from bcf.core import InputError

if TYPE_CHECKING:
    import numpy as np

    from bcf.core import BC6HTexture

CONTAINER_WRITERS = {".dds": "DDS", ".ktx2": "KTX2"}


def size(width: int, height: int) -> str:
    return f"{width}x{height}"


def warn(message: str) -> None:
    print(f"bcf: warning: {message}", file=sys.stderr)


def _levels(count: int) -> str:
    return f"{count} level" + ("s" if count != 1 else "")


def _read_texture(path: Path) -> "BC6HTexture":
    from bcf.core import read_texture

    if not path.exists():
        raise InputError("no such file", file=path)
    if not path.is_file():
        raise InputError("not a regular file", file=path)
    return read_texture(path)


def encode(image: Path, /, *, output: Output, mode: Literal[10, 11, "auto"] = 10, signed: bool = False,
           levels: Annotated[Optional[PositiveInt], Parameter(group=EXCLUSIVE)] = None,
           no_mips: Annotated[bool, Parameter(group=EXCLUSIVE)] = False, verify: bool = False) -> int:
    """Compress an image (EXR, PNG, JPEG, ...) to a mipmapped BC6H texture (.dds or .ktx2).

    Args:
        image: input image; channels as stored, no colour conversion
        output: output texture: .dds or .ktx2
        mode: BC6H mode: 10 = two regions, 6-bit endpoints, 3-bit indices; 11 = one region, 10-bit endpoints,
            4-bit indices; auto = each block in whichever of the 14 modes fits it best
        signed: BC6H_SF16 (keeps negative values); default BC6H_UF16
        levels: number of mip levels (default: all)
        no_mips: level 0 only
        verify: read the file back, decode every level and print PSNR and max error per level
    """
    from bcf.core import (atomic_path, encode_mips, encoder_modes, format_name, full_mip_count, mip_chain, read_rgb,
                          to_bc6h_range, write_dds, write_ktx2)

    container = CONTAINER_WRITERS[check_output_file(output, tuple(CONTAINER_WRITERS), "texture")]
    source = read_rgb(image)
    height, width = source.shape[:2]
    full = full_mip_count(width, height)
    count = 1 if no_mips else (levels or full)
    if count > full:
        raise InputError(f"--levels {count}: {image} is {size(width, height)}, which has at most {full} mip levels")
    converted, problems = to_bc6h_range(source, signed)
    for problem in problems:
        warn(f"{image}: {problem}")
    fmt = format_name(signed)
    say(f"encoding {image} ({size(width, height)}) as {fmt} mode {mode}, {_levels(count)}")
    start = time.perf_counter()
    mips = mip_chain(converted, count)

    def progress(level: int, blocks: "np.ndarray", seconds: float) -> None:
        h, w = mips[level].shape[:2]
        say(f"  level {level}: {size(w, h):>11}  {blocks.shape[0] * blocks.shape[1]:>7} blocks  {seconds:6.2f} s")

    texture = encode_mips(mips, encoder_modes(mode), signed, on_level=progress)
    with atomic_path(output) as temporary:
        (write_dds if container == "DDS" else write_ktx2)(temporary, texture)
    data = sum(level.nbytes for level in texture.levels)
    say(f"wrote {output}: {container} {fmt}, {size(width, height)}, {_levels(count)}, mode {mode}, "
        f"{output.stat().st_size} bytes ({data} of blocks), {time.perf_counter() - start:.2f} s")
    if verify:
        _print_verification(output, mips)
    return 0


def _print_verification(path: Path, mips: Sequence["np.ndarray"]) -> None:
    """Read `path` back and print the per-level quality against the encoder's input mips."""
    from bcf.core import read_texture, verify_texture

    say(f"verify {path} (decoded vs. source mip; PSNR peak = max(1, source max)):")
    say(f"  {'level':>5}  {'size':>11}  {'PSNR (dB)':>9}  {'max abs err':>11}")
    for check in verify_texture(read_texture(path), mips):
        say(f"  {check.level:>5}  {size(check.width, check.height):>11}  {check.psnr_db:>9.2f}"
            f"  {check.max_abs_error:>11.4g}")


def decode(file: Path, /, *, output: Output, level: NonNegativeInt = 0) -> int:
    """Decode one mip level of a BC6H texture to an image (.exr or .png).

    Args:
        file: BC6H texture (.dds or .ktx2, detected by content)
        output: .exr (half float, exact) or .png (16-bit, clamped to [0, 1])
        level: mip level
    """
    from bcf.core import WRITE_EXTENSIONS, atomic_path, decode_image, write_rgb

    suffix = check_output_file(output, tuple(WRITE_EXTENSIONS), "image")
    texture = _read_texture(file)
    if level >= len(texture.levels):
        raise InputError(f"--level {level} does not exist; the file has levels 0..{len(texture.levels) - 1}",
                         file=file)
    width, height = texture.level_size(level)
    decoded = decode_image(texture.levels[level], width, height, texture.signed)
    if suffix == ".png" and (decoded.min() < 0 or decoded.max() > 1):
        warn(f"{output}: PNG holds [0, 1]; values in [{float(decoded.min()):g}, {float(decoded.max()):g}] "
             "are clamped (use .exr to keep them)")
    with atomic_path(output) as temporary:
        write_rgb(temporary, decoded)
    say(f"wrote {output}: level {level} ({size(width, height)}) of {file}")
    return 0


def info(file: Path, /) -> int:
    """Describe a BC6H texture: container, format, levels and the block modes of level 0.

    Args:
        file: BC6H texture (.dds or .ktx2, detected by content)
    """
    from bcf.core import container_kind, format_name, mode_histogram

    texture = _read_texture(file)
    histogram = mode_histogram(texture.levels[0])
    total = sum(histogram.values())
    lines = [f"file:      {file} ({file.stat().st_size} bytes)", f"container: {container_kind(file)}",
             f"format:    {format_name(texture.signed)}", f"size:      {size(texture.width, texture.height)}",
             f"levels:    {len(texture.levels)}", f"  {'level':>5}  {'size':>11}  {'blocks':>8}  {'bytes':>10}"]
    for i, blocks in enumerate(texture.levels):
        lines.append(f"  {i:>5}  {size(*texture.level_size(i)):>11}  {blocks.shape[0] * blocks.shape[1]:>8}"
                     f"  {blocks.nbytes:>10}")
    lines.append("level 0 block modes:")
    for mode, count in histogram.items():
        label = "reserved" if mode == "reserved" else f"mode {mode}"
        lines.append(f"  {label}: {count} blocks ({100.0 * count / total:.1f} %)")
    say("\n".join(lines))
    return 0


COMMANDS = (encode, decode, info)
