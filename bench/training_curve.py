"""Quality vs wall time of the two-phase fit on one material (docs/BENCHMARKS.md).

Trains with a preset (iteration counts overridable) and, every --eval-every iterations, evaluates the
current model exactly as the report does for exported files (texel centres of every mip, PSNR of the mean
MSE over mips, outputs clamped to [0, 1]). Phase-2 models decode their block features bit-exactly, so
the numbers equal those of the exported files up to the fp16 rounding of the weights. Evaluation time is
excluded from the wall-clock column. The start of phase 2 and its last point also have the report's 1 spp
jittered score; `start_kept` says whether the fit returned its start because phase 2 ended below it at texel
centres (the last point is phase 2's own result either way). With --eval-every 0 only those two are scored.

    .venv/bin/python bench/training_curve.py ../shared/materials/wood_peeling_paint_weathered \
        --preset default --phase2-iterations 10000 --eval-every 1000 -o bench/results/curve_wood.json

A material inside a folder with an index.json (../shared/materials) is read through the index, as `bcf bench`
reads it (roles, normal convention, wrap or clamp addressing); --max-size box-filters it down as `bcf bench
--max-size` does.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from bcf.core.material.texture_set import TextureSet, load_material, load_texture_set
from bcf.jobs.bench import INDEX_FILE, downscale, find_materials
from bcf.core.report import metrics
from bcf.core.report import report_json as report
from bcf.core.fit import training
from bcf.core.options import CompressOptions, resolve_options
from bcf.core.pipeline import JITTER_SEED
from bcf.core.fit.sampling import ReferenceMaterial


def load_material_entry(path: Path, max_size: int | None) -> tuple[TextureSet, str | None]:
    """The material at `path` and its addressing from the index (None: the preset's), downscaled to max_size."""
    address = None
    if (path.parent / INDEX_FILE).is_file():
        entry = find_materials(path.parent, [path.name])[0]
        texture_set, address = load_texture_set(entry.files, entry.name), entry.address
    else:
        texture_set = load_material(path)
    return (downscale(texture_set, max_size) if max_size else texture_set), address


def _value(text: str) -> object:
    """An --set value as JSON where it parses (numbers, true/false), else the string itself: pydantic would take
    "0.5" for a float but not "32" for Literal[16, 32]."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material", type=Path)
    parser.add_argument("--preset", default="default")
    parser.add_argument("--features", default="1k")
    parser.add_argument("--phase1-iterations", type=int)
    parser.add_argument("--phase2-iterations", type=int)
    parser.add_argument("--block-mode", type=int, choices=(10, 11))
    parser.add_argument("--batch-size", type=int)
    parser.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                        help="any other CompressOptions field, e.g. --set continuous_fraction=0.25")
    parser.add_argument("--max-size", type=int, help="box-filter the material down to at most this size")
    parser.add_argument("--eval-every", type=int, default=1000)
    parser.add_argument("--rescale-decay", action="store_true",
                        help="recompute both decays so the learning rates end where the preset's do (8.2 %% and "
                             "13.5 %% of the start) after the given iteration counts")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("-o", "--output", type=Path)
    args = parser.parse_args()

    texture_set, address = load_material_entry(args.material, args.max_size)
    overrides = {k: v for k, v in {"phase1_iterations": args.phase1_iterations,
                                   "phase2_iterations": args.phase2_iterations, "block_mode": args.block_mode,
                                   "batch_size": args.batch_size}.items() if v is not None}
    overrides.update((key, _value(text)) for key, text in (item.split("=", 1) for item in args.set))
    options = resolve_options(CompressOptions(preset=args.preset, features=args.features, device=args.device,
                                              **overrides, **({"address": address} if address else {})))
    if args.rescale_decay:
        options = options.model_copy(update={
            "decay_phase1": 0.082 ** (1 / max(options.phase1_iterations, 1)),
            "decay_phase2": 0.135 ** (1 / max(options.phase2_iterations, 1))})
    reference = ReferenceMaterial(texture_set.channels, options.address)
    sizes = [(m.shape[2], m.shape[1]) for m in reference.mips]
    points: list[dict] = []
    start = time.perf_counter()
    evaluation_s = 0.0

    def checkpoint(phase: int, iteration: int, model: training.NeuralMaterial) -> None:
        nonlocal evaluation_s
        t0 = time.perf_counter()
        wall = t0 - start - evaluation_s
        model_cpu = model if args.device == "cpu" else model.to("cpu")
        summary = report.summarise(metrics.evaluate(model_cpu.eval(), reference), sizes)
        if args.device != "cpu":
            model.to(args.device)
        model.train()
        point = {"phase": phase, "iteration": iteration, "wall_s": round(wall, 2),
                 "psnr_all": round(summary.aggregate.psnr.all, 3), "ssim_all": round(summary.aggregate.ssim.all, 4),
                 "psnr": summary.aggregate.psnr.model_dump(),
                 "psnr_per_mip": [round(m.psnr.all, 2) for m in summary.per_mip]}
        if phase == 2 and iteration in (0, options.phase2_iterations):  # the 1 spp score of start and end
            jittered = report.summarise(metrics.evaluate(model_cpu, reference, JITTER_SEED), sizes)
            point["jittered_psnr_all"] = round(jittered.aggregate.psnr.all, 3)
        points.append(point)
        print(json.dumps(point), flush=True)
        evaluation_s += time.perf_counter() - t0

    result = training.fit(texture_set, options, checkpoint=checkpoint, checkpoint_every=args.eval_every)
    out = {"material": texture_set.source.name, "size": [texture_set.width, texture_set.height],
           "options": options.model_dump(), "phase1_s": result.phase1_s, "phase2_s": result.phase2_s,
           "evaluation_s": evaluation_s, "start_kept": result.start_kept, "points": points}
    print(json.dumps({"start_kept": result.start_kept}), flush=True)
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
