"""`bcf compress`, `decode`, `info`, `bench`, `check`, `shader`: the neural-material commands (thin layer over
bcf.core, bcf.jobs.bench and bcf.engine.shader)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Callable, Literal, Optional, TextIO, TypeVar

from cyclopts import Group, Parameter
from cyclopts.types import NonNegativeInt, PositiveFloat, PositiveInt

from bcf.cli import EXCLUSIVE, OptionalOutput, Output, Quiet, clock, model_flags, say
from bcf.core import ROLES, CompressOptions, InputError, JobOptions, MaterialFiles

if TYPE_CHECKING:
    from bcf.core import TextureSet, TrainingProgress

T = TypeVar("T")

FILES = Group("texture files (instead of, or overriding, MATERIAL_DIR)")
TRAINING = Group("training")
TRAINING_FIELDS = ("preset", "features", "address", "device", "seed", "hidden", "block_mode", "init",
                   "phase1_iterations", "phase2_iterations", "batch_size", "continuous_fraction", "centre_fraction",
                   "normal_convention")

# --------------------------------------------------------------------------------------------- progress


class ProgressDisplay:
    """One-line progress bar on a terminal (redrawn in place), or a line every 10 s when not a terminal."""

    def __init__(self, stream: TextIO = sys.stderr, width: int = 28):
        self.stream, self.width = stream, width
        self.tty = stream.isatty()
        self.last_line = 0.0
        self.open = False

    def __call__(self, p: "TrainingProgress") -> None:
        filled = int(p.iteration / max(p.total, 1) * self.width)
        text = (f"phase {p.phase}/2 [{'#' * filled + '.' * (self.width - filled)}] {p.iteration}/{p.total}  "
                f"{p.psnr:5.2f} dB  {p.iterations_per_s:6.1f} it/s  ETA {clock(p.eta_s)}")
        if self.tty:
            self.open = p.iteration < p.total
            self.stream.write("\r" + text + "\x1b[K" + ("" if self.open else "\n"))
            self.stream.flush()
        elif time.monotonic() - self.last_line >= 10.0 or p.iteration == p.total:
            self.stream.write(text + "\n")
            self.stream.flush()
            self.last_line = time.monotonic()

    def close(self) -> None:
        if self.open:
            self.stream.write("\n")
            self.stream.flush()
            self.open = False


def _with_progress(quiet: bool, kept: str, work: Callable[[Optional[ProgressDisplay]], T]) -> T:
    """Run `work` with a progress display (none if `quiet`); Ctrl-C ends the command (exit code 130) with a
    line saying what was kept."""
    display = None if quiet else ProgressDisplay()
    try:
        return work(display)
    except KeyboardInterrupt:
        raise KeyboardInterrupt(kept) from None
    finally:
        if display:
            display.close()


# --------------------------------------------------------------------------------------------- commands


def _describe(texture_set: "TextureSet") -> list[str]:
    source = texture_set.source
    lines = [f"material {source.name}: {source.width}x{source.height}, normal convention "
             f"{source.normal_convention}, ARM {'packed' if source.arm_packed else 'from separate maps'}"]
    for f in source.files:
        lines.append(f"  {f.role:<10} {f.name} ({f.width}x{f.height}, {f.channels} ch, {f.format} {f.bits})")
    for role, value in source.defaults.items():
        lines.append(f"  {role:<10} (none: constant {value:g})")
    return lines + [f"  note: {note}" for note in texture_set.notes]


def compress(material_dir: Optional[Path] = None, /, *, output: Output,
             files: Annotated[MaterialFiles, model_flags(*ROLES, group=FILES)] = MaterialFiles(),
             options: Annotated[JobOptions, model_flags(*TRAINING_FIELDS, group=TRAINING)] = JobOptions(),
             baselines: Annotated[Optional[list[str]], Parameter(consume_multiple=(0, 1))] = None,
             max_pixels: Optional[PositiveInt] = None, memory_budget_mb: Optional[PositiveFloat] = None,
             force: bool = False, quiet: Quiet = False) -> int:
    """Compress a PBR material (albedo, normal, ARM) into BC6H neural features + decoder weights.

    Roles given explicitly override those found in MATERIAL_DIR. Missing AO is 1, missing metalness 0.

    Args:
        material_dir: folder with the material's textures, found by common naming (Poly Haven, ambientCG, ...)
        output: output folder (created)
        baselines: also encode and score conventional codecs into report.json/report.html and OUT/baselines/:
            all (the default when no LIST is given), or a comma-separated list of bc, astc, naive and names
            such as bc1_bc5_full, astc_12x12_half, naive_bc6
        max_pixels: largest texture accepted, width x height, checked from the file headers before any pixel
            is decoded (default: 67108864, 8192x8192)
        memory_budget_mb: refuse a material whose compression needs an estimated peak memory above this, in MiB,
            checked from the file headers before any pixel is decoded (default: this machine's physical memory)
        force: replace OUT if it exists and is not empty
    """
    from bcf.core import (MAX_TEXTURE_PIXELS, check_memory, check_output, compress_material, decode_texture_set,
                          format_report, inspect_texture_set, physical_memory, resolve_material, resolve_options)

    if material_dir is None and files.albedo is None:
        raise InputError("give a MATERIAL_DIR or the texture files (--albedo, --normal, --arm ...)")
    # `--baselines` alone means all; the model checks the names.
    job = JobOptions(**options.model_dump(exclude={"baselines"}),
                     baselines=[] if baselines is None else [",".join(baselines) or "all"])
    check_output(output, force)
    found = resolve_material(material_dir, files.model_copy(update={"normal_convention": job.normal_convention}))
    inspected = inspect_texture_set(found, name=None if material_dir is None else Path(material_dir).resolve().name,
                                    max_pixels=max_pixels or MAX_TEXTURE_PIXELS)
    resolved = resolve_options(job.compress_options())
    budget = int(memory_budget_mb * 2**20) if memory_budget_mb else physical_memory()
    check_memory(inspected.source.width, inspected.source.height, resolved, budget, "--memory-budget-mb")
    texture_set = decode_texture_set(inspected)
    for line in _describe(texture_set):
        say(line)
    say(f"training: preset {resolved.preset}, features {resolved.features}, BC6H mode {resolved.block_mode}, "
        f"{resolved.init} start, MLP 12-{resolved.hidden}-8, {resolved.phase1_iterations} + "
        f"{resolved.phase2_iterations} iterations of {resolved.batch_size} samples on {resolved.device}")
    result = _with_progress(quiet, f"nothing written to {output}", lambda display: compress_material(
        texture_set, resolved, output, progress=display, overwrite=force, baselines=job.baselines,
        note=None if quiet else say))
    say(format_report(result, f"wrote {output} (report.json):"))
    return 0


def decode(folder: Path, /, *, output: Output, mip: Annotated[NonNegativeInt, Parameter(group=EXCLUSIVE)] = 0,
           all_mips: Annotated[bool, Parameter(group=EXCLUSIVE)] = False, format: Literal["png", "exr"] = "png",
           bits: Literal[8, 16] = 8) -> int:
    """Reconstruct albedo / normal / ARM images from a compressed material folder.

    Writes albedo.png, normal.png, arm.png for mip 0 and `albedo_mip<N>.png` etc. for mip N (.exr with
    --format exr).

    Args:
        folder: a folder written by 'bcf compress'
        output: folder for the images (created)
        mip: mip level
        all_mips: every mip level
        format: image format
        bits: PNG bits per channel
    """
    from bcf.core import decode_export, read_manifest

    mips = list(range(read_manifest(folder).mips)) if all_mips else [mip]
    decode_export(folder, output, mips, f".{format}", bits, on_file=lambda path: say(f"wrote {path}"))
    return 0


def info(folder: Path, /) -> int:
    """Describe a compressed material folder (sizes, textures, decoder, quality).

    Args:
        folder: a folder written by 'bcf compress'
    """
    from bcf.core import REPORT_FILE, format_report, read_manifest, read_report, verify_files

    m = read_manifest(folder)
    checked = verify_files(folder, m)
    lines = [f"folder:    {folder}", f"format:    {m.format} v{m.format_version} ({m.generator})",
             f"material:  {m.material.name}, {m.width}x{m.height}, {m.mips} mips, {m.address} addressing, "
             f"normal {m.material.normal_convention}",
             f"training:  preset {m.options.preset}, features {m.options.features}, BC6H mode {m.options.block_mode}, "
             f"{m.options.init} start, {m.options.phase1_iterations} + {m.options.phase2_iterations} iterations, "
             f"seed {m.options.seed}",
             "features:"]
    for t in m.feature_textures:
        lines.append(f"  {t.file}: {t.format} {t.width}x{t.height}, {t.mips} mips, LOD bias {t.lod_bias:+g}, "
                     f"{t.bytes:,} bytes, MLP inputs {t.mlp_inputs[0]}-{t.mlp_inputs[-1]}")
    shape = "-".join([str(m.decoder.layers[0].inputs)] + [str(layer.outputs) for layer in m.decoder.layers])
    lines.append(f"decoder:   {m.decoder.file}: MLP {shape} ({', '.join(x.activation for x in m.decoder.layers)}), "
                 f"{m.decoder.dtype}, {m.decoder.bytes} bytes")
    lines.append("outputs:   " + "; ".join(f"{o.name} = outputs {o.channels[0]}-{o.channels[-1]}" for o in m.outputs))
    lines.append(f"files:     the {checked} files the manifest lists match their SHA-256 and sizes")
    if (folder / REPORT_FILE).is_file():
        lines += ["", format_report(read_report(folder), "quality (report.json):")]
    else:
        lines.append("no report.json")
    say("\n".join(lines))
    return 0


def bench(materials_dir: Path, /, *, output: Output,
          options: Annotated[CompressOptions, model_flags("preset", "device")] = CompressOptions(),
          features: str = "0.5k,1k,2k", baselines: str = "all", max_size: Optional[PositiveInt] = None,
          only: Optional[str] = None, quiet: Quiet = False) -> int:
    """Benchmark: compress every material of a folder at several feature sizes with the BC/ASTC baselines and
    write a Table 2-style summary.

    Writes `DIR/<material>/<features>/` (bcf compress folders), DIR/bench.md, bench.csv, bench.json and
    bench.png. Finished materials are kept when run again with the same options, so an interrupted benchmark
    continues.

    Args:
        materials_dir: folder of material folders (with an index.json naming the roles, or found by file names)
        output: output folder (created)
        features: comma-separated feature sizes
        baselines: baselines as for 'bcf compress --baselines', or none
        max_size: box-filter larger materials down to at most N texels a side first (quicker benchmarks)
        only: comma-separated material names (default: all)
    """
    from bcf.core import parse_baselines
    from bcf.jobs.bench import BenchError, run_bench, write_bench_outputs

    sizes = [f.strip() for f in features.split(",")]
    bad = [f for f in sizes if f not in ("0.5k", "1k", "2k")]
    if bad:
        raise BenchError(f"--features: unknown size {', '.join(bad)}; use 0.5k, 1k, 2k")
    try:
        chosen = [] if baselines == "none" else parse_baselines(baselines)
    except ValueError as exc:
        raise BenchError(f"--baselines: {exc}") from None
    if max_size is not None and max_size < 64:
        raise BenchError(f"--max-size must be at least 64 (the smallest material bcf compresses), got {max_size}")
    started = time.perf_counter()
    reports = _with_progress(quiet, f"finished materials are kept in {output}", lambda display: run_bench(
        materials_dir, output, options.preset, sizes, chosen, max_size,
        [m.strip() for m in only.split(",")] if only else None, options.device, note=None if quiet else say,
        progress=display))
    scale = f", materials box-filtered to at most {max_size} texels a side" if max_size else ""
    header = f"# bcf bench: {len(reports)} materials from {materials_dir.name}, preset {options.preset}{scale}"
    paths = write_bench_outputs(output, reports, header)
    say((output / "bench.md").read_text())
    say(f"wrote {', '.join(str(p) for p in paths)} in {time.perf_counter() - started:.0f} s")
    return 0


def check(report: Path, /, *, baseline: Path, tolerance_db: float = 0.25, update: bool = False) -> int:
    """Regression gate: compare a report.json with a stored baseline per mip and texture (exit 1 if worse).

    Exit codes: 0 nothing got worse, 1 some PSNR dropped by more than the tolerance, 2 the reports cannot be
    compared (malformed, other material, other preset, other mips) or a file is missing.

    Args:
        report: a 'bcf compress' folder, or its report.json
        baseline: the stored report to compare with
        tolerance_db: allowed PSNR drop per mip and texture
        update: write the report as the new baseline instead
    """
    from bcf.core import CheckError, compare_reports, format_check, read_report, write_text_atomic

    if tolerance_db < 0:
        raise CheckError(f"--tolerance-db must be >= 0, got {tolerance_db:g}")
    current = read_report(report)
    if update:
        write_text_atomic(baseline, current.model_dump_json(indent=2) + "\n")
        say(f"wrote baseline {baseline} ({current.material.name}, preset {current.options.preset}, "
            f"{len(current.per_mip)} mips, aggregate PSNR {current.aggregate.psnr.all:.2f} dB)")
        return 0
    rows = compare_reports(current, read_report(baseline), tolerance_db)
    say(format_check(rows, tolerance_db))
    return 1 if any(r.worse for r in rows) else 0


def shader(folder: Path, /, *, lang: Literal["glsl", "hlsl"], output: OptionalOutput = None) -> int:
    """Generate a GLSL or HLSL decoder (BC6H sampling + the MLP with baked weights) for a compressed folder.

    The code declares the four feature textures and defines bcf_decode(uv) (hardware LOD),
    bcf_decode_lod(uv, s) and bcf_decode_grad(uv, dx, dy); docs/FORMAT.md explains how to bind and call it.

    Args:
        folder: a folder written by 'bcf compress'
        lang: shading language
        output: write here instead of to standard output
    """
    from bcf.engine.shader import shader_source

    source = shader_source(folder, lang)
    if output is None:
        sys.stdout.write(source)
        return 0
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(source)
    print(f"wrote {output} ({lang.upper()}, {len(source.splitlines())} lines)", file=sys.stderr)
    return 0


COMMANDS = (compress, decode, info, bench, check, shader)
