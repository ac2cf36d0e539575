"""`bcf compress`, `bcf decode`, `bcf info`: the neural-material commands (thin layer over bcf.core).

Domain errors from the library (bad material files, a corrupt export folder, an output that exists) are
turned into UserError, so they print as one `bcf: error: ...` line with exit code 2.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, TextIO, TypeVar

from bcf.core.material.roles import MaterialError, MaterialFiles
from bcf.core.material.texture_set import TextureSet, load_material

if TYPE_CHECKING:
    from bcf.core.fit.training import TrainingProgress

T = TypeVar("T")

COMMANDS = {
    "compress": "compress a PBR material (albedo, normal, ARM) into BC6H neural features + decoder weights",
    "decode": "reconstruct albedo / normal / ARM images from a compressed material folder",
    "info": "describe a compressed material folder (sizes, textures, decoder, quality)",
    "bench": "benchmark: compress every material of a folder at several feature sizes with the BC/ASTC baselines "
             "and write a Table 2-style summary",
    "check": "regression gate: compare a report.json with a stored baseline per mip and texture (exit 1 if worse)",
    "shader": "generate a GLSL or HLSL decoder (BC6H sampling + the MLP with baked weights) for a compressed folder",
}
ROLE_OPTIONS = ("albedo", "normal", "arm", "ao", "roughness", "metalness")
SCHEDULE_OPTIONS = ("phase1_iterations", "phase2_iterations", "batch_size", "hidden", "block_mode")


def add_commands(commands: argparse._SubParsersAction, user_error: type[Exception],
                 positive_int: Callable[[str], int], non_negative_int: Callable[[str], int]) -> None:
    """Register the three commands on the top-level sub-parser."""
    guard = functools.partial(_guarded, user_error=user_error)

    p = commands.add_parser("compress", help=COMMANDS["compress"], description=COMMANDS["compress"] + ".",
                            epilog="Roles given explicitly override those found in MATERIAL_DIR. Missing AO is 1, "
                                   "missing metalness 0.")
    p.add_argument("material", metavar="MATERIAL_DIR", nargs="?",
                   help="folder with the material's textures, found by common naming (Poly Haven, ambientCG, ...)")
    p.add_argument("-o", "--output", metavar="OUT", required=True, help="output folder (created)")
    files = p.add_argument_group("texture files (instead of, or overriding, MATERIAL_DIR)")
    for role in ROLE_OPTIONS:
        files.add_argument(f"--{role}", metavar="FILE", type=Path)
    files.add_argument("--normal-convention", choices=("opengl", "directx"),
                       help="green channel convention of the normal map (default: from the file name, else opengl)")
    training = p.add_argument_group("training")
    training.add_argument("--preset", choices=("fast", "default", "paper"), default="default",
                          help="training schedule (default: default; fast for previews, paper = the paper's 205k "
                               "iterations)")
    training.add_argument("--features", choices=("0.5k", "1k", "2k"), default="1k",
                          help="T0 at 1/4, 1/2 or 1x the material width (default: 1k)")
    training.add_argument("--address", choices=("wrap", "clamp"), default="wrap",
                          help="texture addressing: wrap for tiling materials (default), clamp for UV atlases")
    training.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    training.add_argument("--seed", type=non_negative_int, default=0, help="random seed (default: 0)")
    training.add_argument("--hidden", type=int, choices=(16, 32), help="MLP hidden width (default: the preset's)")
    training.add_argument("--block-mode", type=int, choices=(10, 11),
                          help="BC6H mode of the feature blocks (default: the preset's)")
    training.add_argument("--phase1-iterations", type=non_negative_int, metavar="N")
    training.add_argument("--phase2-iterations", type=non_negative_int, metavar="N")
    training.add_argument("--batch-size", type=positive_int, metavar="N", help="samples per iteration")
    p.add_argument("--baselines", nargs="?", const="all", metavar="LIST",
                   help="also encode and score conventional codecs into report.json/report.html and "
                        "OUT/baselines/: all (the default when no LIST is given), or a comma-separated list of "
                        "bc, astc, naive and names such as bc1_bc5_full, astc_12x12_half, naive_bc6")
    p.add_argument("--force", action="store_true", help="replace OUT if it exists and is not empty")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    p.set_defaults(handler=functools.partial(guard, handler=_compress))

    p = commands.add_parser("decode", help=COMMANDS["decode"], description=COMMANDS["decode"] + ".",
                            epilog="Writes albedo.png, normal.png, arm.png for mip 0 and albedo_mip<N>.png etc. "
                                   "for mip N (.exr with --format exr).")
    p.add_argument("folder", metavar="OUT", help="a folder written by 'bcf compress'")
    p.add_argument("-o", "--output", metavar="DIR", required=True, help="folder for the images (created)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--mip", type=non_negative_int, default=0, metavar="N", help="mip level (default: 0)")
    which.add_argument("--all-mips", action="store_true", help="every mip level")
    p.add_argument("--format", choices=("png", "exr"), default="png", help="image format (default: png)")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="PNG bits per channel (default: 8)")
    p.set_defaults(handler=functools.partial(guard, handler=_decode))

    p = commands.add_parser("info", help=COMMANDS["info"], description=COMMANDS["info"] + ".")
    p.add_argument("folder", metavar="OUT", help="a folder written by 'bcf compress'")
    p.set_defaults(handler=functools.partial(guard, handler=_info))

    p = commands.add_parser("bench", help=COMMANDS["bench"], description=COMMANDS["bench"] + ".",
                            epilog="Writes DIR/<material>/<features>/ (bcf compress folders), DIR/bench.md, bench.csv, "
                                   "bench.json and bench.png. Finished materials are kept when run again with the "
                                   "same options, so an interrupted benchmark continues.")
    p.add_argument("materials", metavar="MATERIALS_DIR",
                   help="folder of material folders (with an index.json naming the roles, or found by file names)")
    p.add_argument("-o", "--output", metavar="DIR", required=True, help="output folder (created)")
    p.add_argument("--preset", choices=("fast", "default", "paper"), default="default")
    p.add_argument("--features", default="0.5k,1k,2k", metavar="LIST",
                   help="comma-separated feature sizes (default: 0.5k,1k,2k)")
    p.add_argument("--baselines", default="all", metavar="LIST",
                   help="baselines as for 'bcf compress --baselines', or none (default: all)")
    p.add_argument("--max-size", type=positive_int, metavar="N",
                   help="box-filter larger materials down to at most N texels a side first (quicker benchmarks)")
    p.add_argument("--only", metavar="LIST", help="comma-separated material names (default: all)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    p.set_defaults(handler=functools.partial(guard, handler=_bench))

    p = commands.add_parser("check", help=COMMANDS["check"], description=COMMANDS["check"] + ".",
                            epilog="Exit codes: 0 nothing got worse, 1 some PSNR dropped by more than the tolerance, "
                                   "2 the reports cannot be compared (malformed, other material, other preset, other "
                                   "mips) or a file is missing.")
    p.add_argument("report", metavar="OUT", help="a 'bcf compress' folder, or its report.json")
    p.add_argument("--baseline", metavar="BASELINE.json", required=True, type=Path,
                   help="the stored report to compare with")
    p.add_argument("--tolerance-db", type=float, default=0.25, metavar="DB",
                   help="allowed PSNR drop per mip and texture (default: 0.25)")
    p.add_argument("--update", action="store_true", help="write the report as the new baseline instead")
    p.set_defaults(handler=functools.partial(guard, handler=_check))


    p = commands.add_parser("shader", help=COMMANDS["shader"], description=COMMANDS["shader"] + ".",
                            epilog="The code declares the four feature textures and defines bcf_decode(uv) (hardware LOD), "
                                   "bcf_decode_lod(uv, s) and bcf_decode_grad(uv, dx, dy); docs/FORMAT.md explains how to "
                                   "bind and call it.")
    p.add_argument("folder", metavar="OUT", help="a folder written by 'bcf compress'")
    p.add_argument("--lang", choices=("glsl", "hlsl"), required=True, help="shading language")
    p.add_argument("-o", "--output", metavar="FILE", type=Path, help="write here instead of to standard output")
    p.set_defaults(handler=functools.partial(guard, handler=_shader))


def _guarded(args: argparse.Namespace, handler: Callable[[argparse.Namespace], int],
             user_error: type[Exception]) -> int:
    from bcf.jobs import bench  # torch: only when a command runs
    from bcf.core.report import check
    from bcf.core import pipeline as compress
    from bcf.core.export import artifacts as export
    from bcf.core.report import report_json as report
    from bcf.core.fit import training

    try:
        return handler(args)
    except (MaterialError, export.ExportError, compress.OutputExistsError,
            training.DeviceUnavailableError, check.CheckError, report.ReportError, bench.BenchError) as exc:
        raise user_error(cli_message(exc)) from None


def cli_message(exc: Exception) -> str:
    """A library error worded for the command line: options as flags (`--force`)."""
    from bcf.core import InputError

    if isinstance(exc, InputError):
        return exc.message(lambda names: "/".join("--" + n.replace("_", "-") for n in names))
    return str(exc)


def _say(message: str = "") -> None:
    print(message, flush=True)


# --------------------------------------------------------------------------------------------- progress


class ProgressDisplay:
    """One-line progress bar on a terminal (redrawn in place), or a line every 10 s when not a terminal."""

    def __init__(self, stream: TextIO = sys.stderr, width: int = 28):
        self.stream = stream
        self.tty = stream.isatty()
        self.width = width
        self.last_line = 0.0
        self.open = False

    def __call__(self, p: "TrainingProgress") -> None:
        done = p.iteration / max(p.total, 1)
        filled = int(done * self.width)
        bar = "#" * filled + "." * (self.width - filled)
        text = (f"phase {p.phase}/2 [{bar}] {p.iteration}/{p.total}  {p.psnr:5.2f} dB  "
                f"{p.iterations_per_s:6.1f} it/s  ETA {_duration(p.eta_s)}")
        if self.tty:
            self.stream.write("\r" + text + "\x1b[K")
            self.open = p.iteration < p.total
            if not self.open:
                self.stream.write("\n")
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


def _with_progress(quiet: bool, after_interrupt: str, work: Callable[[ProgressDisplay | None], T]) -> T:
    """Run `work` with a progress display (none if `quiet`); Ctrl-C ends the command with exit code 130 and a
    line saying what was kept."""
    display = None if quiet else ProgressDisplay()
    try:
        return work(display)
    except KeyboardInterrupt:
        if display:
            display.close()
        print(f"bcf: interrupted; {after_interrupt}", file=sys.stderr)
        raise SystemExit(130) from None
    finally:
        if display:
            display.close()


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


# --------------------------------------------------------------------------------------------- commands


def _explicit_files(args: argparse.Namespace) -> MaterialFiles:
    roles = {role: getattr(args, role) for role in ROLE_OPTIONS if getattr(args, role) is not None}
    return MaterialFiles(**roles, normal_convention=args.normal_convention)


def _describe(texture_set: TextureSet) -> list[str]:
    source = texture_set.source
    lines = [f"material {source.name}: {source.width}x{source.height}, normal convention "
             f"{source.normal_convention}, ARM {'packed' if source.arm_packed else 'from separate maps'}"]
    for f in source.files:
        lines.append(f"  {f.role:<10} {f.name} ({f.width}x{f.height}, {f.channels} ch, {f.format} {f.bits})")
    for role, value in source.defaults.items():
        lines.append(f"  {role:<10} (none: constant {value:g})")
    return lines


def _compress(args: argparse.Namespace) -> int:
    from bcf.core.options import parse_baselines
    from bcf.core import pipeline as compress
    from bcf.core.report import report_json as report
    from bcf.core.options import JobOptions, resolve_options

    if args.material is None and args.albedo is None:
        raise MaterialError("give a MATERIAL_DIR or the texture files (--albedo, --normal, --arm ...)")
    try:
        baselines = [] if args.baselines is None else parse_baselines(args.baselines)
    except ValueError as exc:
        raise MaterialError(f"--baselines: {exc}") from None
    output = Path(args.output)
    compress.check_output(output, args.force)
    texture_set = load_material(Path(args.material) if args.material else None, _explicit_files(args))
    for line in _describe(texture_set):
        _say(line)
    for note in texture_set.notes:
        _say(f"  note: {note}")
    overrides = {k: getattr(args, k) for k in SCHEDULE_OPTIONS if getattr(args, k) is not None}
    options = JobOptions(preset=args.preset, features=args.features, address=args.address, device=args.device,
                         seed=args.seed, baselines=baselines, normal_convention=args.normal_convention, **overrides)
    resolved = resolve_options(options.compress_options())
    _say(f"training: preset {resolved.preset}, features {resolved.features}, BC6H mode {resolved.block_mode}, "
         f"MLP 12-{resolved.hidden}-8, {resolved.phase1_iterations} + {resolved.phase2_iterations} iterations "
         f"of {resolved.batch_size} samples on {resolved.device}")
    result = _with_progress(args.quiet, f"nothing written to {output}", lambda display: compress.compress_material(
        texture_set, resolved, output, progress=display, overwrite=args.force, baselines=options.baselines,
        note=None if args.quiet else _say))
    _say(report.format_report(result, f"wrote {output} (report.json):"))
    return 0


def _decode(args: argparse.Namespace) -> int:
    from bcf.core import decode_export
    from bcf.core import pipeline as compress
    from bcf.core.export import artifacts as export

    folder = Path(args.folder)
    manifest = export.read_manifest(folder)
    mips = list(range(manifest.mips)) if args.all_mips else [args.mip]
    extension = ".exr" if args.format == "exr" else ".png"
    decode_export(folder, Path(args.output), mips, extension, args.bits,
                           on_file=lambda path: _say(f"wrote {path}"))
    return 0


def _info(args: argparse.Namespace) -> int:
    from bcf.core.export import artifacts as export
    from bcf.core.report import report_json as report

    folder = Path(args.folder)
    m = export.read_manifest(folder)
    lines = [f"folder:    {folder}", f"format:    {m.format} v{m.format_version} ({m.generator})",
             f"material:  {m.material.name}, {m.width}x{m.height}, {m.mips} mips, {m.address} addressing, "
             f"normal {m.material.normal_convention}",
             f"training:  preset {m.options.preset}, features {m.options.features}, BC6H mode {m.options.block_mode}, "
             f"{m.options.phase1_iterations} + {m.options.phase2_iterations} iterations, seed {m.options.seed}",
             "features:"]
    for t in m.feature_textures:
        lines.append(f"  {t.file}: {t.format} {t.width}x{t.height}, {t.mips} mips, LOD bias {t.lod_bias:+g}, "
                     f"{t.bytes:,} bytes, MLP inputs {t.mlp_inputs[0]}-{t.mlp_inputs[-1]}")
    shape = "-".join([str(m.decoder.layers[0].inputs)] + [str(l.outputs) for l in m.decoder.layers])
    lines.append(f"decoder:   {m.decoder.file}: MLP {shape} ({', '.join(l.activation for l in m.decoder.layers)}), "
                 f"{m.decoder.dtype}, {m.decoder.bytes} bytes")
    lines.append("outputs:   " + "; ".join(f"{o.name} = outputs {o.channels[0]}-{o.channels[-1]}" for o in m.outputs))
    if (folder / report.REPORT_FILE).is_file():
        lines += ["", report.format_report(report.read_report(folder), "quality (report.json):")]
    else:
        lines.append("no report.json")
    _say("\n".join(lines))
    return 0


def _bench(args: argparse.Namespace) -> int:
    from bcf.core.options import parse_baselines
    from bcf.jobs import bench

    sizes = [f.strip() for f in args.features.split(",")]
    bad = [f for f in sizes if f not in ("0.5k", "1k", "2k")]
    if bad or not sizes:
        raise bench.BenchError(f"--features: unknown size {', '.join(bad)}; use 0.5k, 1k, 2k")
    try:
        baselines = [] if args.baselines == "none" else parse_baselines(args.baselines)
    except ValueError as exc:
        raise bench.BenchError(f"--baselines: {exc}") from None
    if args.max_size is not None and args.max_size < 64:
        raise bench.BenchError(f"--max-size must be at least 64 (the smallest material bcf compresses), "
                               f"got {args.max_size}")
    only = [m.strip() for m in args.only.split(",")] if args.only else None
    output = Path(args.output)
    started = time.perf_counter()
    reports = _with_progress(args.quiet, f"finished materials are kept in {output}", lambda display: bench.run_bench(
        Path(args.materials), output, args.preset, sizes, baselines, args.max_size, only, args.device,
        note=None if args.quiet else _say, progress=display))
    scale = f", materials box-filtered to at most {args.max_size} texels a side" if args.max_size else ""
    header = (f"# bcf bench: {len(reports)} materials from {Path(args.materials).name}, preset {args.preset}"
              f"{scale}")
    paths = bench.write_bench_outputs(output, reports, header)
    _say((output / "bench.md").read_text())
    _say(f"wrote {', '.join(str(p) for p in paths)} in {time.perf_counter() - started:.0f} s")
    return 0


def _check(args: argparse.Namespace) -> int:
    from bcf.core.report import check
    from bcf.core.report import report_json as report

    if args.tolerance_db < 0:
        raise check.CheckError(f"--tolerance-db must be >= 0, got {args.tolerance_db:g}")
    current = report.read_report(Path(args.report))
    if args.update:
        baseline = args.baseline
        baseline.parent.mkdir(parents=True, exist_ok=True)
        temporary = baseline.with_name(f".{baseline.name}.tmp")
        temporary.write_text(current.model_dump_json(indent=2) + "\n")
        temporary.replace(baseline)
        _say(f"wrote baseline {baseline} ({current.material.name}, preset {current.options.preset}, "
             f"{len(current.per_mip)} mips, aggregate PSNR {current.aggregate.psnr.all:.2f} dB)")
        return 0
    rows = check.compare_reports(current, report.read_report(args.baseline), args.tolerance_db)
    _say(check.format_check(rows, args.tolerance_db))
    return 1 if any(r.worse for r in rows) else 0


def _shader(args: argparse.Namespace) -> int:
    from bcf.engine import shader

    source = shader.shader_source(Path(args.folder), args.lang)
    if args.output is None:
        sys.stdout.write(source)
        return 0
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(source)
    print(f"wrote {args.output} ({args.lang.upper()}, {len(source.splitlines())} lines)", file=sys.stderr)
    return 0
