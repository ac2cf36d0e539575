"""`bcf bench`: compress every material of a folder at several feature sizes, with the conventional baselines,
and summarise like the paper's Table 2 (PSNR, SSIM, size per method over the whole set) and Fig. 9.

Layout of the output folder::

    DIR/<material>/<features>/   a normal `bcf compress` folder (report.json, report.html, baselines/ ...)
    DIR/bench.md, bench.csv      the table: one row per method, over all materials; then per material
    DIR/bench.json               the same numbers, machine-readable
    DIR/bench.png                PSNR vs size (Fig. 9)

A material whose folder already holds a report.json made from the same input files at the same size with the
same options is not recompressed, so an interrupted benchmark continues where it stopped.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from bcf.core import (ROLES, CompressOptions, FeatureSize, InputError, MaterialFiles, MaterialSource, MipMetrics,
                      Preset, ProgressCallback, Report, ReportError, TextureSet, compress_material, is_current,
                      load_texture_set, mip_chain, psnr_from_mse, read_report, resolve_material, result_identity)

__all__ = ["BenchError", "BenchMaterial", "MethodSummary", "find_materials", "downscale", "run_bench",
           "summarise_bench", "write_bench_outputs"]

INDEX_FILE = "index.json"
NoteCallback = Callable[[str], None]


class BenchError(InputError):
    """A materials folder that holds no usable material, or a bad benchmark option."""


@dataclass(frozen=True)
class BenchMaterial:
    name: str
    files: MaterialFiles
    address: str  # wrap for tiling materials, clamp for UV atlases


def _from_index(root: Path, index: dict) -> list[BenchMaterial]:
    """index.json (see ../shared/materials): {"materials": {name: {role: file, "normal_convention", "layout"}}}."""
    found = []
    for name, entry in sorted(index.get("materials", {}).items()):
        roles = {role: root / name / entry[role] for role in ROLES if role in entry}
        files = MaterialFiles(**roles, normal_convention=entry.get("normal_convention"))
        found.append(BenchMaterial(name, files, "clamp" if entry.get("layout") == "uv-atlas" else "wrap"))
    return found


def find_materials(root: Path, only: Optional[Sequence[str]] = None) -> list[BenchMaterial]:
    """The materials of `root`: from its index.json when there is one (roles, normal convention and layout
    as stated there), else every sub-folder whose files discovery can assign (wrap addressing)."""
    root = Path(root)
    if not root.is_dir():
        raise BenchError(f"{root}: not a folder")
    index = root / INDEX_FILE
    if index.is_file():
        try:
            found = _from_index(root, json.loads(index.read_text()))
        except (ValueError, KeyError, TypeError) as exc:
            raise BenchError(f"{index}: not a materials index ({exc})") from None
    else:
        found = [BenchMaterial(d.name, resolve_material(d, MaterialFiles()), "wrap")
                 for d in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))]
    if only:
        unknown = sorted(set(only) - {m.name for m in found})
        if unknown:
            raise BenchError(f"{root}: no material named {', '.join(unknown)}")
        found = [m for m in found if m.name in only]
    if not found:
        raise BenchError(f"{root}: no materials found (sub-folders with albedo, normal, ARM textures, or index.json)")
    return found


def downscale(texture_set: TextureSet, max_size: int) -> TextureSet:
    """Box-filter the material down (by whole mip levels) until neither side exceeds `max_size`."""
    levels = 1
    while max(texture_set.width, texture_set.height) >> (levels - 1) > max_size:
        levels += 1
    if levels == 1:
        return texture_set
    channels = mip_chain(texture_set.channels, levels)[-1]
    h, w = channels.shape[:2]
    source = texture_set.source.model_copy(update={"width": w, "height": h})
    note = f"downscaled from {texture_set.width}x{texture_set.height} to {w}x{h} for the benchmark"
    return TextureSet(channels, source, texture_set.notes + (note,))


# --------------------------------------------------------------------------------------------------- run


def _kept_report(folder: Path, options: CompressOptions, source: MaterialSource,
                 baselines: Sequence[str]) -> Optional[Report]:
    """The report of a finished earlier run in `folder` that is still current (`bcf.core.is_current`: same inputs
    at the same size, so a different --max-size or a changed file recompresses, same options, at least the
    wanted baselines); else None."""
    try:
        previous = read_report(folder)
    except ReportError:
        return None
    wanted = result_identity({f.role: f.sha256 for f in source.files}, source.normal_convention,
                             (source.width, source.height), options)
    return previous if is_current(previous, wanted, baselines) else None


def run_bench(root: Path, output: Path, preset: Preset = "default",
              features: Sequence[FeatureSize] = ("0.5k", "1k", "2k"), baselines: Sequence[str] = (),
              max_size: Optional[int] = None, only: Optional[Sequence[str]] = None, device: str = "cpu",
              note: Optional[NoteCallback] = None,
              progress: Optional[ProgressCallback] = None) -> dict[str, dict[str, Report]]:
    """Compress every material at every feature size into output/<material>/<features>/; the BC/ASTC
    baselines run with the first feature size (they do not depend on it), naive_bc6 with every one.
    Returns {material: {features: report}}."""
    say = note or (lambda message: None)
    materials = find_materials(root, only)
    codec_baselines = [b for b in baselines if b != "naive_bc6"]
    reports: dict[str, dict[str, Report]] = {}
    started = time.perf_counter()
    for number, entry in enumerate(materials, 1):
        texture_set = load_texture_set(entry.files, entry.name)
        if max_size is not None:
            texture_set = downscale(texture_set, max_size)
        reports[entry.name] = {}
        for i, size in enumerate(features):
            folder = Path(output) / entry.name / size
            options = CompressOptions(preset=preset, features=size, address=entry.address, device=device)
            wanted = (codec_baselines if i == 0 else []) + (["naive_bc6"] if "naive_bc6" in baselines else [])
            kept = _kept_report(folder, options, texture_set.source, wanted)
            if kept is not None:
                say(f"[{number}/{len(materials)}] {entry.name} {size}: done before, kept")
            else:
                say(f"[{number}/{len(materials)}] {entry.name} {size}: {texture_set.width}x{texture_set.height}, "
                    f"{entry.address} ({time.perf_counter() - started:.0f} s so far)")
                kept = compress_material(texture_set, options, folder, progress=progress, overwrite=True,
                                         baselines=wanted)
            reports[entry.name][size] = kept
    return reports


# ----------------------------------------------------------------------------------------------- summary


@dataclass(frozen=True)
class MethodSummary:
    """One row of the Table 2-style summary: a method over all materials."""

    method: str  # "BCf-1k", "bc1_bc5_full", ...
    psnr: float  # of the mean over materials of each material's mean MSE over mips (paper Table 2)
    psnr_albedo: float
    psnr_normal: float
    psnr_arm: float
    ssim: float  # mean over materials of the mean SSIM over mips
    mib: float  # mean size per material, MiB
    bits_per_texel: float  # mean over materials
    materials: int


def _mean_mse(per_mip: Sequence[MipMetrics], texture: str) -> float:
    return float(np.mean([getattr(m.mse, texture) for m in per_mip]))


MethodEntry = tuple[str, list[MipMetrics], float, float, int]  # material, per_mip, ssim, bits/texel, bytes


def _method_rows(reports: dict[str, dict[str, Report]]) -> dict[str, list[MethodEntry]]:
    """method -> [(material, per_mip, ssim, bits_per_texel, bytes)] for ours (per feature size) and every baseline
    (naive_bc6 per feature size too)."""
    rows: dict[str, list[MethodEntry]] = {}
    for name, by_size in reports.items():
        for size, rep in by_size.items():
            rows.setdefault(f"BCf-{size}", []).append(
                (name, rep.per_mip, rep.aggregate.ssim.all, rep.size.bits_per_texel, rep.size.total_bytes))
            for baseline, b in rep.baselines.items():
                method = f"naive_bc6-{size}" if baseline == "naive_bc6" else baseline
                rows.setdefault(method, []).append((name, b.per_mip, b.aggregate.ssim.all, b.bits_per_texel,
                                                    b.size_bytes))
    return rows


def summarise_bench(reports: dict[str, dict[str, Report]]) -> list[MethodSummary]:
    """Table 2: every method over the materials it ran on, smallest first."""
    summary = []
    for method, entries in _method_rows(reports).items():
        psnr = {t: psnr_from_mse(float(np.mean([_mean_mse(e[1], t) for e in entries])))
                for t in ("all", "albedo", "normal", "arm")}
        summary.append(MethodSummary(method, psnr["all"], psnr["albedo"], psnr["normal"], psnr["arm"],
                                     float(np.mean([e[2] for e in entries])),
                                     float(np.mean([e[4] for e in entries])) / 2**20,
                                     float(np.mean([e[3] for e in entries])), len(entries)))
    return sorted(summary, key=lambda s: (s.mib, s.method))


def _per_material_table(reports: dict[str, dict[str, Report]]) -> list[str]:
    methods = sorted(_method_rows(reports))
    lines = ["| material | size | " + " | ".join(methods) + " |", "|---|---|" + "---:|" * len(methods)]
    for name, by_size in reports.items():
        cells = {}
        for method, entries in _method_rows({name: by_size}).items():
            cells[method] = f"{psnr_from_mse(_mean_mse(entries[0][1], 'all')):.2f}"
        first = next(iter(by_size.values()))
        lines.append(f"| {name} | {first.material.width}x{first.material.height} | "
                     + " | ".join(cells.get(m, "") for m in methods) + " |")
    return lines


def _markdown(summary: Sequence[MethodSummary], reports: dict[str, dict[str, Report]],
              header: str) -> str:
    lines = [header, "",
             "| method | PSNR (dB) | albedo | normal | ARM | SSIM | MiB per material | bits/texel | materials |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in summary:
        lines.append(f"| {s.method} | {s.psnr:.2f} | {s.psnr_albedo:.2f} | {s.psnr_normal:.2f} | {s.psnr_arm:.2f} | "
                     f"{s.ssim:.3f} | {s.mib:.3f} | {s.bits_per_texel:.2f} | {s.materials} |")
    lines += ["", "PSNR: of the mean over materials of each material's mean MSE over mips (all 8 channels); "
              "SSIM: mean over materials and mips.", "", "Per material, PSNR (dB) over all mips:", ""]
    lines += _per_material_table(reports)
    return "\n".join(lines) + "\n"


def _csv(summary: Sequence[MethodSummary]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["method", "psnr_db", "psnr_albedo_db", "psnr_normal_db", "psnr_arm_db", "ssim",
                     "mib_per_material", "bits_per_texel", "materials"])
    for s in summary:
        writer.writerow([s.method, f"{s.psnr:.4f}", f"{s.psnr_albedo:.4f}", f"{s.psnr_normal:.4f}",
                         f"{s.psnr_arm:.4f}", f"{s.ssim:.5f}", f"{s.mib:.5f}", f"{s.bits_per_texel:.4f}", s.materials])
    return buffer.getvalue()


def _plot(summary: Sequence[MethodSummary], path: Path, title: str) -> None:
    """PSNR vs size, one labelled point per method (the paper's Fig. 9)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    figure = Figure(figsize=(7.5, 4.8), dpi=110)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    for s in summary:
        ours = s.method.startswith("BCf-")
        axes.scatter([s.mib], [s.psnr], s=60 if ours else 35, marker="*" if ours else "o",
                     color="tab:red" if ours else "tab:gray" if s.method.startswith("naive") else "tab:blue",
                     zorder=3)
        # Ours labelled below left, the rest above right: ours often sits right next to ASTC 12x12.
        axes.annotate(s.method, (s.mib, s.psnr), textcoords="offset points", xytext=(-6, -12) if ours else (5, 4),
                      ha="right" if ours else "left", fontsize=8, color="tab:red" if ours else "black")
    axes.set_xscale("log")
    axes.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))  # 1-2-5 ticks, labelled plainly
    axes.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    axes.xaxis.set_minor_formatter(NullFormatter())
    axes.set_xlabel("size per material (MiB, with mips, log scale)")
    axes.set_ylabel("PSNR over all mips (dB)")
    axes.set_title(title, fontsize=10)
    axes.grid(True, which="both", alpha=0.3)
    figure.tight_layout()
    figure.savefig(path)


def write_bench_outputs(output: Path, reports: dict[str, dict[str, Report]], header: str) -> list[Path]:
    """bench.md, bench.csv, bench.json and bench.png in `output`."""
    summary = summarise_bench(reports)
    output.mkdir(parents=True, exist_ok=True)
    paths = [output / "bench.md", output / "bench.csv", output / "bench.json", output / "bench.png"]
    paths[0].write_text(_markdown(summary, reports, header))
    paths[1].write_text(_csv(summary))
    paths[2].write_text(json.dumps({"header": header, "methods": [vars(s) for s in summary],
                                    "materials": {name: {size: str(Path(name) / size) for size in by_size}
                                                  for name, by_size in reports.items()}}, indent=2) + "\n")
    _plot(summary, paths[3], header.lstrip("# "))
    return paths
