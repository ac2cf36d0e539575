"""`bcf check`, the per-mip regression gate, on a real report (a tiny real compress) and edited copies."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from bcf.core import REPORT_FILE
from bcf_command import run_bcf


def edited_baseline(folder: Path, target: Path, edit: Callable[[dict[str, Any]], None]) -> Path:
    data = json.loads((folder / REPORT_FILE).read_text())
    edit(data)
    target.write_text(json.dumps(data))
    return target


def test_identical_reports_pass_and_print_the_table(export_folder: Path, tmp_path: Path) -> None:
    baseline = tmp_path / "baseline.json"
    result = run_bcf("check", export_folder, "--baseline", baseline, "--update")
    assert result.returncode == 0, result.stderr
    assert json.loads(baseline.read_text()) == json.loads((export_folder / "report.json").read_text())
    result = run_bcf("check", export_folder / "report.json", "--baseline", baseline)
    assert result.returncode == 0, result.stderr
    mips = len(json.loads(baseline.read_text())["per_mip"])
    assert result.stdout.count("+0.00") == 4 * (mips + 1)  # every mip and the aggregate, 4 textures each
    assert "OK:" in result.stdout and "WORSE" not in result.stdout


def test_a_one_db_drop_at_one_mip_fails(export_folder: Path, tmp_path: Path) -> None:
    # The baseline was 1 dB better on the normal map at mip 1: the current report is worse there.
    def better_normal_mip1(data: dict[str, Any]) -> None:
        data["per_mip"][1]["psnr"]["normal"] += 1.0

    baseline = edited_baseline(export_folder, tmp_path / "baseline.json", better_normal_mip1)
    result = run_bcf("check", export_folder, "--baseline", baseline)
    assert result.returncode == 1, (result.stdout, result.stderr)
    worse = [line for line in result.stdout.splitlines() if line.endswith("WORSE")]
    assert len(worse) == 1 and worse[0].split()[:2] == ["1", "normal"], result.stdout
    assert "-1.00" in worse[0] and "FAIL: 1 of" in result.stdout
    # Within a larger tolerance the same drop passes; improvements never fail.
    assert run_bcf("check", export_folder, "--baseline", baseline, "--tolerance-db", "1.5").returncode == 0

    def worse_everywhere(data: dict[str, Any]) -> None:
        for mip in data["per_mip"]:
            for name in mip["psnr"]:
                mip["psnr"][name] -= 3.0

    better = edited_baseline(export_folder, tmp_path / "lower.json", worse_everywhere)
    assert run_bcf("check", export_folder, "--baseline", better).returncode == 0


@pytest.mark.parametrize("case", ["malformed", "not a report", "missing", "other preset", "missing mip",
                                  "other material", "changed input"])
def test_incomparable_baselines_are_errors(case: str, export_folder: Path, tmp_path: Path) -> None:
    path = tmp_path / "baseline.json"
    edits: dict[str, Callable[[dict[str, Any]], None]] = {
        "other preset": lambda d: d["options"].update(preset="default"),
        "missing mip": lambda d: d["per_mip"].pop(),
        "other material": lambda d: d["material"].update(name="bricks"),
        "changed input": lambda d: d["material"]["files"][0].update(sha256="0" * 64),
    }
    if case == "malformed":
        path.write_text('{"per_mip": [')
    elif case == "not a report":
        path.write_text(json.dumps({"hello": 1}))
    elif case in edits:
        edited_baseline(export_folder, path, edits[case])
    result = run_bcf("check", export_folder, "--baseline", path)
    assert result.returncode == 2, (case, result.stdout, result.stderr)
    assert result.stderr.startswith("bcf: error:") and result.stderr.count("\n") == 1, result.stderr
    expected = {"malformed": "not a bcf report", "not a report": "not a bcf report", "missing": "no such file",
                "other preset": "different preset", "missing mip": "mips differ",
                "other material": "different material", "changed input": "different material"}[case]
    assert expected in result.stderr, result.stderr


@pytest.mark.parametrize("value", [float("nan"), "NaN", float("inf"), "-Infinity"])
@pytest.mark.parametrize("which", ["baseline", "report"])
def test_a_score_that_is_not_a_number_is_an_error(value: object, which: str, export_folder: Path,
                                                  tmp_path: Path) -> None:
    """NaN or infinite PSNR, as a JSON number or a string, in the report or in the baseline: never a pass."""
    def poison(data: dict[str, Any]) -> None:
        data["per_mip"][0]["psnr"]["all"] = value

    edited = edited_baseline(export_folder, tmp_path / "edited.json", poison)
    pristine = export_folder / REPORT_FILE
    report, baseline = (pristine, edited) if which == "baseline" else (edited, pristine)
    result = run_bcf("check", report, "--baseline", baseline)
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert result.stderr.startswith("bcf: error:") and result.stderr.count("\n") == 1, result.stderr
    assert "not a bcf report" in result.stderr and "per_mip.0.psnr.all" in result.stderr, result.stderr


def test_check_reads_exactly_the_scores_in_the_report(export_folder: Path, tmp_path: Path) -> None:
    from bcf.core.report import check
    from bcf.core.report import report_json as report_io

    report = report_io.read_report(export_folder)
    rows = check.compare_reports(report, report, 0.25)
    per_mip = [r for r in rows if r.mip is not None]
    assert len(per_mip) == 4 * len(report.per_mip) and len(rows) == len(per_mip) + 4
    values = np.array([r.current_db for r in per_mip]).reshape(len(report.per_mip), 4)
    expected = np.array([[m.psnr.albedo, m.psnr.normal, m.psnr.arm, m.psnr.all] for m in report.per_mip])
    np.testing.assert_array_equal(values, expected)
