"""report.json: the quality, size and timing of one compressed material, and its terminal table.

Every score comes from decoding the exported files (`export.load_export`), except the `models` entries,
which evaluate the training-time models to show what export costs (paper Fig. 8).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from bcf.core.errors import InputError
from bcf.core.material.texture_set import MaterialSource
from bcf.core.options import ResolvedOptions
from bcf.core.psnr import psnr_from_mse
from bcf.core.report.metrics import MipScores

__all__ = ["REPORT_FILE", "Aggregate", "BaselineReport", "Evaluation", "MipMetrics", "Report", "ReportError",
           "SizeReport", "TextureScores", "TimingReport", "bc1_bc5_bytes", "format_baselines", "format_report",
           "read_report", "summarise"]

REPORT_FILE = "report.json"


class ReportError(InputError):
    """A report.json that is missing or is not a bcf report; the message names the file."""


class _Model(BaseModel):
    # Scores are always finite (psnr_from_mse caps an exact match at MAX_PSNR_DB): a NaN or an infinity, as a
    # number or a string, is a damaged report, and `bcf check` must never pass one.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# Counts and sizes are non-negative and exact as floats (the table divides and formats them): a damaged
# report is a ReportError, never an overflow; seconds and rates are never negative.
Count = Annotated[int, Field(ge=0, le=2**53)]
NonNegative = Annotated[float, Field(ge=0)]


class TextureScores(_Model):
    albedo: float
    normal: float
    arm: float
    all: float


class MipMetrics(_Model):
    mip: Count
    width: Count
    height: Count
    psnr: TextureScores
    ssim: TextureScores
    mse: TextureScores


class Aggregate(_Model):
    """psnr: of the mean MSE over mips; ssim: mean over mips."""

    psnr: TextureScores
    ssim: TextureScores


class Evaluation(_Model):
    aggregate: Aggregate
    per_mip: list[MipMetrics]


class SizeReport(_Model):
    total_bytes: Count  # features + weights: what a renderer keeps in memory
    features_bytes: Count  # BC6H blocks of all mips of the four feature textures
    weights_bytes: Count  # decoder.bin
    files_bytes: Count  # everything in the output folder on disk (headers, manifest, report included)
    bits_per_texel: NonNegative  # total_bytes * 8 / (material width * height)
    bc1_bc5_bytes: Count  # BC1 albedo + BC1 ARM + BC5 normal with full mip chains, at the material's size


class TimingReport(_Model):
    phase1_s: NonNegative
    transition_s: NonNegative
    phase2_s: NonNegative
    export_s: NonNegative
    evaluation_s: NonNegative
    total_s: NonNegative


class HistoryEntry(_Model):
    phase: Count
    iteration: Count
    elapsed_s: NonNegative
    psnr: float  # running training PSNR (random batches), dB


class BaselineReport(_Model):
    """A conventional codec (or the naive BC6 variant of our own features), decoded and scored with the same
    metric code at the same texel centres of every reference mip as `Report.per_mip`."""

    description: str  # what was encoded how, e.g. "BC1 albedo + ARM, BC5 normal at 1024x1024, mips to 1x1"
    encoder: str  # library and settings, e.g. "quicktex 0.3.1, level 18"
    width: Count  # resolution of the baseline's top mip (half the material's for the *_half baselines)
    height: Count
    aggregate: Aggregate
    per_mip: list[MipMetrics]
    size_bytes: Count  # every block of every mip (down to 1x1 for BC/ASTC), what a renderer keeps in memory
    bits_per_texel: NonNegative  # size_bytes * 8 / (material width * height)
    encode_s: NonNegative
    evaluation_s: NonNegative


class Report(_Model):
    generator: str
    created_at: str
    device: str
    material: MaterialSource
    options: ResolvedOptions
    aggregate: Aggregate  # exported files, texel centres of every mip
    per_mip: list[MipMetrics]
    jittered: Evaluation  # exported files, 1 random sample per pixel against the filtered reference (§6.2)
    models: dict[str, Aggregate]  # exported / trained_fp32 / phase1_unconstrained
    mean_baseline: Aggregate  # the per-channel mean everywhere: the floor any decoder must clear
    size: SizeReport
    timing: TimingReport
    history: list[HistoryEntry]
    # Phase 2 ended below its start at texel centres, so the export holds the start (the transition's blocks).
    # Default: False, as reports written before the fit made this choice always hold phase 2's result.
    start_kept: bool = False
    baselines: dict[str, BaselineReport] = {}  # `bcf compress --baselines`: name -> scores and size


def _scores(values: dict[str, float]) -> TextureScores:
    return TextureScores(**values)


def summarise(mips: list[MipScores], sizes: list[tuple[int, int]]) -> Evaluation:
    """Per-mip scores -> per-mip entries and the paper's aggregate (PSNR of the mean MSE; mean SSIM)."""
    per_mip = [MipMetrics(mip=i, width=w, height=h, psnr=_scores(m["psnr"]), ssim=_scores(m["ssim"]),
                          mse=_scores(m["mse"])) for i, (m, (w, h)) in enumerate(zip(mips, sizes))]
    names = list(TextureScores.model_fields)
    psnr = {n: psnr_from_mse(sum(m["mse"][n] for m in mips) / len(mips)) for n in names}
    ssim = {n: sum(m["ssim"][n] for m in mips) / len(mips) for n in names}
    return Evaluation(aggregate=Aggregate(psnr=_scores(psnr), ssim=_scores(ssim)), per_mip=per_mip)


def bc1_bc5_bytes(width: int, height: int) -> int:
    """Bytes of the usual BC textures for the material: BC1 (8 bytes / block) albedo and ARM plus BC5
    (16 bytes / block) normal, each with a full mip chain down to 1x1 (partial blocks padded)."""
    total, level = 0, 0
    while True:
        w, h = max(1, width >> level), max(1, height >> level)
        total += math.ceil(w / 4) * math.ceil(h / 4) * (8 + 8 + 16)
        if w == 1 and h == 1:
            return total
        level += 1


def _row(cells: list[str], widths: list[int]) -> str:
    return "  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))


def format_report(report: Report, title: Optional[str] = None) -> str:
    """The report as a plain-text table (per mip PSNR / SSIM per texture, aggregates, sizes, times)."""
    names = ["albedo", "normal", "arm", "all"]
    header = ["mip", "size"] + [f"PSNR {n}" for n in names] + ["SSIM all"]
    rows = [[str(m.mip), f"{m.width}x{m.height}"] + [f"{getattr(m.psnr, n):.2f}" for n in names]
            + [f"{m.ssim.all:.4f}"] for m in report.per_mip]
    a = report.aggregate
    rows.append(["all", "mean"] + [f"{getattr(a.psnr, n):.2f}" for n in names] + [f"{a.ssim.all:.4f}"])
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    lines = [title] if title else []
    lines += [_row(header, widths)] + [_row(r, widths) for r in rows]
    lines.append("")
    lines.append(f"1 spp (jittered) PSNR all: {report.jittered.aggregate.psnr.all:.2f} dB; "
                 + ", ".join(f"{k}: {v.psnr.all:.2f} dB" for k, v in report.models.items())
                 + f"; per-channel mean: {report.mean_baseline.psnr.all:.2f} dB")
    if report.baselines:
        lines += ["", format_baselines(report)]
    s, t = report.size, report.timing
    lines.append(f"size: {s.total_bytes / 2**20:.3f} MiB ({s.features_bytes:,} B features + {s.weights_bytes:,} B "
                 f"weights, {s.bits_per_texel:.2f} bits/texel); BC1+BC5 at this size: {s.bc1_bc5_bytes / 2**20:.3f} MiB")
    lines.append(f"time: start and phase 1 {t.phase1_s:.1f} s, transition {t.transition_s:.1f} s, phase 2 "
                 f"{t.phase2_s:.1f} s, export {t.export_s:.1f} s, "
                 f"evaluation {t.evaluation_s:.1f} s, total {t.total_s:.1f} s on {report.device}")
    if report.start_kept:
        lines.append("phase 2 ended below its start at texel centres: the export holds the start")
    return "\n".join(lines)


def format_baselines(report: Report) -> str:
    """Ours and every baseline, smallest first: aggregate PSNR per texture, SSIM, size."""
    names = ["albedo", "normal", "arm", "all"]
    entries = [("ours", report.aggregate, report.size.total_bytes, report.size.bits_per_texel)]
    entries += [(k, b.aggregate, b.size_bytes, b.bits_per_texel) for k, b in report.baselines.items()]
    header = ["method"] + [f"PSNR {n}" for n in names] + ["SSIM all", "MiB", "bits/texel"]
    rows = [[name] + [f"{getattr(a.psnr, n):.2f}" for n in names] + [f"{a.ssim.all:.4f}", f"{size / 2**20:.3f}",
            f"{bits:.2f}"] for name, a, size, bits in sorted(entries, key=lambda e: (e[2], e[0]))]
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    return "\n".join([_row(header, widths)] + [_row(r, widths) for r in rows])


def read_report(path: Path) -> Report:
    """Read a report.json, given as the file or as the 'bcf compress' folder holding it."""
    path = Path(path)
    file = path / REPORT_FILE if path.is_dir() else path
    if not file.is_file():
        raise ReportError("no such file", file=file)
    try:
        return Report.model_validate_json(file.read_bytes())
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        raise ReportError(f"not a bcf report ({where}: {first['msg']})", file=file) from None
