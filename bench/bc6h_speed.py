"""Speed and quality of the BC6H codec on one real texture; prints a Markdown table.

Usage: .venv/bin/python bench/bc6h_speed.py [IMAGE] [--runs N]

Times (best of N runs, default 3) on IMAGE (default: the 2048x2048 albedo of the Poly Haven set
wood_peeling_paint_weathered): `partition.fit_lines` (partition search, regions=2), `partition.encode_image` in
mode 10, mode 11 and with every mode (auto: each block in the best), and `bc6h.decode_blocks` of each result;
PSNR (peak = max(1, image max)) per mode.
The image is used as stored (8-bit sRGB values in [0, 1], no linearisation), level 0 only.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np
import torch

from bcf.core.codec import bc6h
from bcf.core.codec import partition
from bcf.core.codec.textures import encoder_modes, psnr
from bcf.core.material.images import read_rgb

DEFAULT_IMAGE = Path("/work/shared/materials/wood_peeling_paint_weathered/wood_peeling_paint_weathered_diff_2k.jpg")
T = TypeVar("T")


def best_of(runs: int, work: Callable[[], T]) -> tuple[float, T]:
    """(fastest wall time in seconds over `runs` calls of `work`, the last result)."""
    best = float("inf")
    result = None
    for _ in range(runs):
        start = time.perf_counter()
        result = work()
        best = min(best, time.perf_counter() - start)
    return best, result  # type: ignore[return-value]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("image", nargs="?", type=Path, default=DEFAULT_IMAGE)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()

    image = read_rgb(args.image)
    height, width = image.shape[:2]
    texels = bc6h.image_to_block_texels(image.astype(np.float64))
    flat = texels.reshape(-1, 16, 3)
    mtexels = width * height / 1e6
    print(f"image: {args.image} ({width}x{height}, {len(flat)} blocks), best of {args.runs} runs")
    print(f"torch.get_num_threads() = {torch.get_num_threads()}, os.cpu_count() = {os.cpu_count()}, "
          f"numpy {np.__version__}, torch {torch.__version__}, Python {platform.python_version()}")
    print()

    rows = []
    seconds, _ = best_of(args.runs, lambda: partition.fit_lines(flat, regions=2, signed=False))
    rows.append(("fit_lines (partition search, regions=2)", "", seconds, ""))
    for mode in (10, 11, "auto"):
        modes = encoder_modes(mode)
        seconds, blocks = best_of(args.runs, lambda: partition.encode_image(image, modes, signed=False))
        decode_seconds, decoded = best_of(args.runs, lambda: bc6h.decode_blocks(blocks, signed=False))
        restored = bc6h.block_texels_to_image(decoded, width, height)
        quality = f"{psnr(image, restored):.2f}"
        rows.append(("encode_image", str(mode), seconds, quality))
        rows.append(("decode_blocks", str(mode), decode_seconds, quality))

    print("| step | mode | best time (s) | Mtexel/s | PSNR (dB) |")
    print("|---|---|---:|---:|---:|")
    for step, mode, seconds, quality in rows:
        print(f"| {step} | {mode} | {seconds:.3f} | {mtexels / seconds:.2f} | {quality} |")


if __name__ == "__main__":
    main()
