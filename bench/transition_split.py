"""Where the phase 1 -> phase 2 transition loses quality (issue 15, lever 1; docs/BENCHMARKS.md).

Trains phase 1 of a preset, then scores the model, exactly as the report scores exported files, with its
features taken step by step towards BC6H mode-11 blocks, each step adding one constraint:

1. phase 1: the unconstrained features;
2. range: each feature channel mapped onto [0, 1] and clipped to its 0.05-99.95 % quantiles (the transition's
   range map; the decoder's input scale and offset undo the mapping);
3. line: every 4x4 block replaced by its points on the block's principal line in the half-bit domain (the
   partition search's segment; float endpoints and float positions);
4. + 4-bit indices: positions rounded to sixteenths of the segment (float endpoints);
5. + 10-bit endpoints: the exact BC6H decode of the blocks the transition writes (phase 2's start).

    .venv/bin/python bench/transition_split.py ../shared/materials/wood_peeling_paint_weathered \
        -o bench/results/issue15/transition_wood_2k.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from bcf.core.codec import bc6h, partition
from bcf.core.fit import model as nm
from bcf.core.fit import training
from bcf.core.fit.block_decode import half_bits_to_value
from bcf.core.fit.sampling import ReferenceMaterial
from bcf.core.options import CompressOptions, resolve_options
from bcf.core.report import metrics
from bcf.core.report import report_json as report
from training_curve import load_material_entry


def _stored_levels(free: nm.FreeFeatures) -> list[list[np.ndarray]]:
    """Every level of every pyramid as the transition stores it: (h, w, 3) in [0, 1] after the range map."""
    pyramids = []
    for i, spec in enumerate(free.specs):
        low, high = nm._feature_range(free, i, shared=False)
        levels = (free.level(i, level).detach().numpy().astype(np.float64).transpose(1, 2, 0)
                  for level in range(spec.levels))
        pyramids.append([np.clip((x - low) / (high - low), 0.0, 1.0) for x in levels])
    return pyramids


def _line_points(stored: np.ndarray, index_bits: int | None) -> np.ndarray:
    """A level (h, w, 3) with every block's pixels moved onto the block's segment in the half-bit domain
    (mode 11's single region), positions optionally rounded to 2^index_bits - 1 steps; endpoints stay real."""
    h, w, _ = stored.shape
    texels = bc6h.image_to_block_texels(stored).reshape(-1, 16, 3)
    fit = partition.fit_lines(texels, 1, signed=False)
    ends = fit.ends[:, 0]  # (n, 2, 3) segment ends in half bits
    weights = fit.weights
    if index_bits is not None:
        top = (1 << index_bits) - 1
        weights = np.floor(weights * top + 0.5) / top
    bits = ends[:, None, 0] + weights[..., None] * (ends[:, None, 1] - ends[:, None, 0])  # (n, 16, 3)
    values = half_bits_to_value(torch.from_numpy(bits)).numpy()  # eq. 9
    return bc6h.block_texels_to_image(values.reshape(h // 4, w // 4, 16, 3), w, h)


def _score(features: nm.Features, decoder: nm.Decoder, reference: ReferenceMaterial, address: str) -> float:
    material = nm.NeuralMaterial(features, decoder, address).eval()
    sizes = [(m.shape[2], m.shape[1]) for m in reference.mips]
    return report.summarise(metrics.evaluate(material, reference), sizes).aggregate.psnr.all


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material", type=Path)
    parser.add_argument("--preset", default="default")
    parser.add_argument("--features", default="1k")
    parser.add_argument("--max-size", type=int, help="box-filter the material down to at most this size")
    parser.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE")
    parser.add_argument("-o", "--output", type=Path)
    args = parser.parse_args()

    texture_set, address = load_material_entry(args.material, args.max_size)
    overrides = dict(item.split("=", 1) for item in args.set)
    options = resolve_options(CompressOptions(preset=args.preset, features=args.features, phase2_iterations=0,
                                              block_mode=11, **overrides, **({"address": address} if address else {})))
    reference = ReferenceMaterial(texture_set.channels, options.address)
    result = training.fit(texture_set, options)
    free, blocks = result.phase1_model.features, result.naive_model.features
    decoder = result.naive_model.decoder  # input scale and offset undo the range map
    stored = _stored_levels(free)

    def static(levels: list[list[np.ndarray]]) -> nm.StaticFeatures:
        return nm.StaticFeatures(free.specs, [[torch.from_numpy(np.ascontiguousarray(
            level.transpose(2, 0, 1))).float() for level in pyramid] for pyramid in levels])

    stages = {
        "phase 1": _score(free, result.phase1_model.decoder, reference, options.address),
        "range": _score(static(stored), decoder, reference, options.address),
        "line": _score(static([[_line_points(x, None) for x in p] for p in stored]), decoder, reference,
                       options.address),
        "+ 4-bit indices": _score(static([[_line_points(x, 4) for x in p] for p in stored]), decoder, reference,
                                  options.address),
        "+ 10-bit endpoints (BC6H)": _score(blocks, decoder, reference, options.address),
    }
    out = {"material": texture_set.source.name, "size": [texture_set.width, texture_set.height],
           "options": options.model_dump(), "psnr_all": stages}
    print(json.dumps(out["psnr_all"], indent=1))
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
