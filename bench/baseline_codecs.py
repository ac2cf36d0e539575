"""The BC/ASTC baselines of one material at its full resolution, without training (docs/BENCHMARKS.md).

Encodes, decodes and scores every codec baseline exactly as `bcf compress --baselines` does, printing one line per
baseline (PSNR all / albedo / normal / ARM, SSIM, size, encode and scoring time) and writing the reports as JSON.

    OMP_NUM_THREADS=1 .venv/bin/python bench/baseline_codecs.py ../shared/materials/wood_peeling_paint_weathered \
        -o bench/results/baselines_wood_2k.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from bcf.core.material.texture_set import load_material
from bcf.core.report import baselines
from bcf.core.options import parse_baselines
from bcf.core.fit.sampling import ReferenceMaterial


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material", type=Path)
    parser.add_argument("-o", "--output", type=Path, required=True, help="JSON file for the baseline reports")
    parser.add_argument("--baselines", default="bc,astc", help="as for bcf compress --baselines (default: bc,astc)")
    args = parser.parse_args()

    texture_set = load_material(args.material)
    reference = ReferenceMaterial(texture_set.channels, "wrap")
    results = {}
    for name in parse_baselines(args.baselines):
        scored, _ = baselines.run_codec_baseline(name, texture_set.channels, reference)
        results[name] = scored.model_dump()
        a = scored.aggregate
        print(f"{name:16s} {a.psnr.all:6.2f} dB (albedo {a.psnr.albedo:5.2f}, normal {a.psnr.normal:5.2f}, "
              f"ARM {a.psnr.arm:5.2f})  SSIM {a.ssim.all:.3f}  {scored.size_bytes / 2**20:7.3f} MiB  "
              f"encode {scored.encode_s:5.1f} s  score {scored.evaluation_s:5.1f} s", flush=True)
    args.output.write_text(json.dumps({"material": texture_set.source.name, "width": texture_set.width,
                                       "height": texture_set.height, "baselines": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
