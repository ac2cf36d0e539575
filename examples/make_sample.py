"""Recreate examples/sample/: small crops of a real Poly Haven material for the demo and the CLI tests.

Usage: .venv/bin/python examples/make_sample.py [MATERIAL_DIR] [OUT_DIR]

For each texture of the set (albedo `*_diff_*`, normal `*_nor_gl_*`, packed AO/rough/metal `*_arm_*`): take the
top-left 512x512 texels, box-filter them 2x down to 256x256 (`bcf.core.mip_chain` level 1: the mean of
each 2x2 texel square, no colour conversion), and save as an 8-bit RGB PNG (values rounded to nearest).
"""

from __future__ import annotations

import sys
from pathlib import Path

from bcf.core import mip_chain, read_rgb, write_rgb

DEFAULT_MATERIAL = Path("/work/shared/materials/wood_peeling_paint_weathered")
DEFAULT_OUT = Path(__file__).resolve().parent / "sample"
CROP = 512
# Output name -> file-name pattern of the Poly Haven set.
ROLES = {"albedo.png": "*_diff_*", "normal_gl.png": "*_nor_gl_*", "arm.png": "*_arm_*"}


def find_texture(material: Path, pattern: str) -> Path:
    """The single file of `material` matching `pattern`."""
    matches = sorted(material.glob(pattern))
    if len(matches) != 1:
        raise SystemExit(f"make_sample: expected one {pattern} in {material}, found {len(matches)}")
    return matches[0]


def make_sample(material: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, pattern in ROLES.items():
        source = find_texture(material, pattern)
        image = read_rgb(source)
        if min(image.shape[:2]) < CROP:
            raise SystemExit(f"make_sample: {source} is smaller than {CROP}x{CROP}")
        half = mip_chain(image[:CROP, :CROP], levels=2)[1]  # (256, 256, 3): 2x2 box average
        write_rgb(out / name, half, png_bits=8)
        print(f"{source.name} -> {out / name} {half.shape[1]}x{half.shape[0]}")


if __name__ == "__main__":
    make_sample(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_MATERIAL,
                Path(sys.argv[2]) if len(sys.argv) > 2 else DEFAULT_OUT)
