"""`bcf bench` end to end on two real materials (tests/data/chainmail_128 and the bundled sample, box-filtered to
64 px): per-material compress folders, the Table 2-style summary (Markdown, CSV, JSON, plot) recomputed from the
reports, resuming, index.json materials and user errors."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from bcf.core.material.texture_set import load_material
from bcf.jobs import bench
from bcf.core.psnr import psnr_from_mse
from bcf.core.report.report_json import read_report
from bcf_command import run_bcf

ROOT = Path(__file__).resolve().parents[1]
CHAINMAIL = ROOT / "tests" / "data" / "chainmail_128"
SAMPLE = ROOT / "examples" / "sample"
BENCH_ARGS = ("--preset", "fast", "--features", "0.5k,1k", "--baselines", "bc,naive", "--max-size", "64")


@pytest.fixture(scope="module")
def materials(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("materials")
    shutil.copytree(CHAINMAIL, root / "chainmail")
    shutil.copytree(SAMPLE, root / "sample")
    return root


@pytest.fixture(scope="module")
def benched(materials: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("bench") / "out"
    result = run_bcf("bench", materials, "-o", out, *BENCH_ARGS, timeout=600)
    assert result.returncode == 0, result.stderr
    return out, result.stdout


def test_every_material_and_feature_size_is_a_compress_folder(benched: tuple[Path, str]) -> None:
    out, _ = benched
    for name in ("chainmail", "sample"):
        first, second = read_report(out / name / "0.5k"), read_report(out / name / "1k")
        assert (first.material.width, first.material.height) == (64, 64)  # box-filtered by --max-size
        assert first.options.features == "0.5k" and second.options.features == "1k"
        # BC/ASTC baselines run once per material (with the first size); naive BC6 with every size.
        assert set(first.baselines) == {"bc1_bc5_full", "bc1_bc5_half", "naive_bc6"}
        assert set(second.baselines) == {"naive_bc6"}
        assert (out / name / "0.5k" / "report.html").is_file()


def test_summary_is_recomputed_from_the_reports(benched: tuple[Path, str]) -> None:
    """PSNR of a method = PSNR of the mean over materials of each material's mean MSE over mips (paper Table 2)."""
    out, stdout = benched
    rows = {r["method"]: r for r in csv.DictReader((out / "bench.csv").open())}
    assert set(rows) == {"BCf-0.5k", "BCf-1k", "bc1_bc5_full", "bc1_bc5_half", "naive_bc6-0.5k", "naive_bc6-1k"}
    reports = [read_report(out / name / "1k") for name in ("chainmail", "sample")]
    expected = psnr_from_mse(float(np.mean([np.mean([m.mse.all for m in r.per_mip]) for r in reports])))
    assert float(rows["BCf-1k"]["psnr_db"]) == pytest.approx(expected, abs=1e-3)
    bc = [read_report(out / name / "0.5k").baselines["bc1_bc5_full"] for name in ("chainmail", "sample")]
    assert float(rows["bc1_bc5_full"]["mib_per_material"]) == pytest.approx(bc[0].size_bytes / 2**20, abs=1e-5)
    assert float(rows["BCf-1k"]["ssim"]) == pytest.approx(np.mean([r.aggregate.ssim.all for r in reports]), abs=1e-4)
    assert all(int(r["materials"]) == 2 for r in rows.values())
    markdown = (out / "bench.md").read_text()
    assert "| BCf-1k |" in markdown and "| chainmail | 64x64 |" in markdown and markdown in stdout + "\n"
    summary = json.loads((out / "bench.json").read_text())
    assert {m["method"] for m in summary["methods"]} == set(rows)
    plot = oiio.ImageBuf(str(out / "bench.png"))
    assert plot.spec().width > 400 and len(np.unique(plot.get_pixels(oiio.UINT8).reshape(-1, 4), axis=0)) > 50


def test_second_run_keeps_finished_materials(materials: Path, benched: tuple[Path, str]) -> None:
    out, _ = benched
    before = {p: p.stat().st_mtime_ns for p in out.glob("*/*/report.json")}
    result = run_bcf("bench", materials, "-o", out, *BENCH_ARGS, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("done before, kept") == 4
    assert {p: p.stat().st_mtime_ns for p in out.glob("*/*/report.json")} == before


def test_other_size_or_options_are_not_kept(materials: Path, benched: tuple[Path, str]) -> None:
    """Resuming keeps a folder only for the same inputs at the same size, the same options and the baselines."""
    out, _ = benched
    texture_set = load_material(materials / "chainmail")
    options = bench.CompressOptions(preset="fast", features="1k")
    same = bench.downscale(texture_set, 64).source
    assert bench._kept_report(out / "chainmail" / "1k", options, same, ["naive_bc6"]) is not None
    assert bench._kept_report(out / "chainmail" / "1k", options, texture_set.source, []) is None  # --max-size 128
    assert bench._kept_report(out / "chainmail" / "1k", options, same, ["bc1_bc5_full"]) is None
    assert bench._kept_report(out / "chainmail" / "1k", bench.CompressOptions(preset="default", features="1k"),
                              same, []) is None


def test_index_json_names_roles_and_layout(tmp_path: Path) -> None:
    """With an index.json, roles, normal convention and layout come from it (uv-atlas -> clamp addressing)."""
    shutil.copytree(CHAINMAIL, tmp_path / "mail")
    files = {p.name for p in (tmp_path / "mail").iterdir()}
    entry = {"resolution": [128, 128], "layout": "uv-atlas", "normal_convention": "opengl",
             **{role: next(f for f in files if f.endswith(f"_{suffix}.png")) for role, suffix in
                (("albedo", "Color"), ("normal", "Normal"), ("roughness", "Roughness"), ("metalness", "Metalness"))}}
    (tmp_path / "index.json").write_text(json.dumps({"materials": {"mail": entry}}))
    [found] = bench.find_materials(tmp_path)
    assert found.name == "mail" and found.address == "clamp"
    assert found.files.normal_convention == "opengl"  # the file name alone would say DirectX (ambientCG)
    assert found.files.albedo == tmp_path / "mail" / entry["albedo"]


def test_downscale_is_the_box_filtered_mip(tmp_path: Path) -> None:
    texture_set = load_material(CHAINMAIL)
    small = bench.downscale(texture_set, 32)
    assert (small.width, small.height) == (32, 32) and (small.source.width, small.source.height) == (32, 32)
    expected = texture_set.channels.reshape(32, 4, 32, 4, 8).mean(axis=(1, 3))
    np.testing.assert_allclose(small.channels, expected, atol=1e-6)
    assert bench.downscale(texture_set, 128) is texture_set


def test_user_errors(tmp_path: Path, materials: Path) -> None:
    (tmp_path / "empty").mkdir()
    for args, message in [((tmp_path / "empty",), "no materials found"),
                          ((materials, "--only", "nope"), "no material named nope"),
                          ((materials, "--features", "3k"), "unknown size 3k"),
                          ((materials, "--max-size", "32"), "--max-size must be at least 64"),
                          ((materials, "--baselines", "etc2"), "unknown baseline 'etc2'")]:
        result = run_bcf("bench", *args, "-o", tmp_path / "out")
        assert result.returncode == 2, (args, result.stderr)
        assert message in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()
