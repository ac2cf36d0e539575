"""Where the time of one training iteration goes (docs/BENCHMARKS.md), for phase 1 and phase 2.

Builds the model of a material like `training.fit` does (phase 2 from a short phase 1), then times
iterations split into: reference sampling, feature decode (phase 2: the BC6H decode of the mips a batch
needs), feature sampling + MLP forward, backward, optimizer step. Also prints torch's profiler table of the
most expensive operators (self CPU time).

    .venv/bin/python bench/profile_iteration.py ../shared/materials/wood_peeling_paint_weathered --iterations 20
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from pathlib import Path

import torch

from bcf.core.material.texture_set import load_material
from bcf.core.fit import model as nm
from bcf.core.fit import training
from bcf.core.fit.batches import BatchSampler
from bcf.core.options import CompressOptions, ResolvedOptions, resolve_options
from bcf.core.fit.sampling import ReferenceMaterial, trilinear_levels


def time_iterations(model: nm.NeuralMaterial, reference: ReferenceMaterial, options: ResolvedOptions,
                    iterations: int, lr: float) -> dict[str, float]:
    optimizer = training.adam_optimizer([{"params": list(model.parameters()), "lr": lr}])
    generator = torch.Generator().manual_seed(0)
    batches = BatchSampler(reference, options.batch_size, options.continuous_fraction, options.centre_fraction,
                           generator, generator)
    parts: dict[str, float] = defaultdict(float)
    for _ in range(iterations):
        t = time.perf_counter()
        batch = batches()
        uv, s, target = batch.uv, batch.s, batch.target
        parts["batch: points + reference"] += time.perf_counter() - t
        t = time.perf_counter()
        if isinstance(model.features, nm.BlockFeatures):
            # Decode the levels this s needs once, then sample through a cache, to time the two apart.
            decoded = {}
            for i, spec in enumerate(model.features.specs):
                low, high, w = trilinear_levels(s + spec.lod_bias, spec.levels)
                for level in {low, high} if w > 0 else {low}:
                    decoded[i, level] = model.features.level(i, level)
            parts["BC6H decode (forward)"] += time.perf_counter() - t
            t = time.perf_counter()
            cached = nm.NeuralMaterial(nm.StaticFeatures(model.features.specs, [[decoded.get((i, l)) for l in
                                       range(spec.levels)] for i, spec in enumerate(model.features.specs)]),
                                       model.decoder, model.address)
            prediction = cached(uv, s)
        else:
            prediction = model(uv, s)
        loss = torch.mean((prediction - target) ** 2)
        parts["sampling + MLP (forward)"] += time.perf_counter() - t
        t = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        parts["backward"] += time.perf_counter() - t
        t = time.perf_counter()
        optimizer.step()
        parts["optimizer step"] += time.perf_counter() - t
    return {k: v / iterations for k, v in parts.items()}


def report(title: str, parts: dict[str, float]) -> None:
    total = sum(parts.values())
    print(f"\n{title}: {1000 * total:.1f} ms per iteration")
    for name, seconds in parts.items():
        print(f"  {name:<28} {1000 * seconds:7.1f} ms  {100 * seconds / total:5.1f} %")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material", type=Path)
    parser.add_argument("--preset", default="default")
    parser.add_argument("--features", default="1k")
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--block-mode", choices=("10", "11", "auto"))
    parser.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                        help="any other CompressOptions field, e.g. --set continuous_fraction=0.25")
    args = parser.parse_args()
    texture_set = load_material(args.material)
    extra: dict[str, object] = {}
    if args.block_mode:
        extra["block_mode"] = args.block_mode if args.block_mode == "auto" else int(args.block_mode)
    extra.update(item.split("=", 1) for item in args.set)
    options = resolve_options(CompressOptions(preset=args.preset, features=args.features, phase1_iterations=20,
                                              phase2_iterations=1, **extra))
    reference = ReferenceMaterial(texture_set.channels, options.address)
    result = training.fit(texture_set, options)
    print(f"{texture_set.source.name} {texture_set.width}x{texture_set.height}, features {options.features}, "
          f"batch {options.batch_size}, torch threads {torch.get_num_threads()}")
    report("phase 1", time_iterations(result.phase1_model, reference, options, args.iterations, 1e-3))
    report("phase 2", time_iterations(result.model, reference, options, args.iterations, 1e-3))
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        time_iterations(result.model, reference, options, 3, 1e-3)
    print("\nphase 2, top operators by self CPU time (3 iterations):")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12))


if __name__ == "__main__":
    main()
