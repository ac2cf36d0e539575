"""The regression gate: compare a fresh report.json with a stored baseline (both read with
`report.read_report`), per mip and per texture.

A comparison is only meaningful between reports of the same material (same input files) and the same preset
over the same mips; anything else is a `CheckError`, never a pass.
"""

from __future__ import annotations

from dataclasses import dataclass

from bcf.core.errors import InputError
from bcf.core.report.report_json import Report, TextureScores

__all__ = ["CheckError", "CheckRow", "compare_reports", "format_check"]

TEXTURE_NAMES = tuple(TextureScores.model_fields)  # albedo, normal, arm, all


class CheckError(InputError):
    """Reports that cannot be compared (malformed, other material, other preset, other mips)."""


@dataclass(frozen=True)
class CheckRow:
    """One score of the comparison. mip is None for the aggregate."""

    mip: int | None
    texture: str
    baseline_db: float
    current_db: float
    worse: bool

    @property
    def delta_db(self) -> float:
        return self.current_db - self.baseline_db


def _inputs(report: Report) -> tuple[str, list[tuple[str, str]]]:
    return report.material.name, sorted((f.role, f.sha256) for f in report.material.files)


def _mip_sizes(report: Report) -> list[tuple[int, int, int]]:
    return [(m.mip, m.width, m.height) for m in report.per_mip]


def _check_comparable(current: Report, baseline: Report) -> None:
    if _inputs(current) != _inputs(baseline):
        raise CheckError(f"different material: the baseline is {baseline.material.name!r} "
                         f"({', '.join(f.name for f in baseline.material.files)}), this report is "
                         f"{current.material.name!r} ({', '.join(f.name for f in current.material.files)}) "
                         "or its input files changed; regenerate the baseline with --update")
    if current.options.preset != baseline.options.preset:
        raise CheckError(f"different preset: baseline {baseline.options.preset!r}, this report "
                         f"{current.options.preset!r}")
    if _mip_sizes(current) != _mip_sizes(baseline):
        missing = sorted(set(_mip_sizes(baseline)) - set(_mip_sizes(current)))
        extra = sorted(set(_mip_sizes(current)) - set(_mip_sizes(baseline)))
        raise CheckError(f"the mips differ: missing from this report {missing or 'none'}, "
                         f"not in the baseline {extra or 'none'}")


def compare_reports(current: Report, baseline: Report, tolerance_db: float) -> list[CheckRow]:
    """PSNR of every (mip, texture) and of the aggregate; a row is worse when it dropped by more than
    `tolerance_db`. Raises CheckError when the reports are not comparable."""
    _check_comparable(current, baseline)
    pairs = [(m.mip, c.psnr, m.psnr) for c, m in zip(current.per_mip, baseline.per_mip)]
    pairs.append((None, current.aggregate.psnr, baseline.aggregate.psnr))
    rows = []
    for mip, now, before in pairs:
        for name in TEXTURE_NAMES:
            a, b = getattr(before, name), getattr(now, name)
            rows.append(CheckRow(mip, name, a, b, b < a - tolerance_db))
    return rows


def format_check(rows: list[CheckRow], tolerance_db: float) -> str:
    """A table of every comparison (worse rows marked), then a one-line verdict."""
    header = f"{'mip':>4}  {'texture':<7}  {'baseline':>8}  {'current':>8}  {'change':>7}"
    lines = [header]
    for r in rows:
        mip = "all" if r.mip is None else str(r.mip)
        mark = "  WORSE" if r.worse else ""
        lines.append(f"{mip:>4}  {r.texture:<7}  {r.baseline_db:8.2f}  {r.current_db:8.2f}  {r.delta_db:+7.2f}{mark}")
    worse = [r for r in rows if r.worse]
    if worse:
        lines.append(f"FAIL: {len(worse)} of {len(rows)} PSNR scores dropped by more than {tolerance_db:g} dB")
    else:
        lines.append(f"OK: no PSNR score dropped by more than {tolerance_db:g} dB ({len(rows)} compared)")
    return "\n".join(lines)
