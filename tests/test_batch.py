"""`bcf batch` end to end on the 21 reference texture sets, rebuilt under their published file names as
64x64 images cut from the real Chainmail004 set (tests/data), so the run is fast and needs no shared data."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import pytest

from bcf.core import load_export
from bcf.core.material.assets import FoundMaterial
from bcf.jobs.batch import _output_names
from bcf_command import BCF, ONE_THREAD_ENV, default_sigint, run_bcf
from service_harness import CHAINMAIL, CHAINMAIL_ROLES, BcfEnvironment

NAMES = json.loads((Path(__file__).parent / "data" / "material_names.json").read_text())["materials"]
ROLES = ("albedo", "normal", "arm", "ao", "roughness", "metalness")
TINY = ["--preset", "fast", "--phase1-iterations", "10", "--phase2-iterations", "10", "--batch-size", "256"]
SIZE = 64


def _read(name: str) -> np.ndarray:
    return oiio.ImageBuf(str(CHAINMAIL / name)).get_pixels(oiio.FLOAT)


def _write(path: Path, pixels: np.ndarray) -> None:
    height, width, channels = pixels.shape
    image = oiio.ImageBuf(oiio.ImageSpec(width, height, channels, oiio.UINT8))
    image.set_pixels(oiio.ROI(0, width, 0, height), np.ascontiguousarray(pixels, dtype=np.float32))
    assert image.write(str(path)), image.geterror()


def _pixels(role: str, shift: int) -> np.ndarray:
    """64x64 real pixels for a role, shifted per material so every material has its own content."""
    def crop(name: str) -> np.ndarray:
        return np.roll(_read(CHAINMAIL_ROLES[name]), shift, axis=1)[:SIZE, :SIZE]

    if role == "albedo":
        return crop("albedo")
    if role == "normal":
        return crop("normal")
    rough, metal = crop("roughness")[..., :1], crop("metalness")[..., :1]
    if role == "arm":
        return np.concatenate([np.ones_like(rough), rough, metal], axis=-1)
    return {"ao": np.clip(rough + 0.3, 0, 1), "roughness": rough, "metalness": metal}.get(role, rough * 0.5)


def build_library(root: Path) -> Path:
    """The 21 material folders with their published names (maps bcf does not use are small grey images)."""
    for number, (name, entry) in enumerate(sorted(NAMES.items())):
        folder = root / name
        folder.mkdir(parents=True)
        roles = {entry[role]: role for role in ROLES if entry.get(role)}
        for file in entry["files"]:
            if Path(file).suffix.lower() in (".jpg", ".png"):
                _write(folder / file, _pixels(roles.get(file, "unused"), 3 * number))
            else:
                (folder / file).write_text("not an image\n")
    return root


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_library(tmp_path_factory.mktemp("assets") / "library")


def summary(out: Path) -> dict[str, Any]:
    return json.loads((out / "batch-summary.json").read_text())


def statuses(out: Path) -> dict[str, str]:
    return {item["material"]: item["status"] for item in summary(out)["items"]}


def test_list_finds_all_21_sets_with_their_roles(library: Path) -> None:
    result = run_bcf("batch", library, "--list", "--json")
    assert result.returncode == 0, result.stderr
    found = {m["material"]: m for m in json.loads(result.stdout)}
    assert sorted(found) == sorted(NAMES)
    for name, entry in NAMES.items():
        m = found[name]
        expected = {role: f"{name}/{entry[role]}" for role in ROLES if entry.get(role)}
        assert {r: f for r, f in m["files"].items() if r in ROLES} == expected, name
        assert m["dir"] == name and m["resolution"] == [SIZE, SIZE] and m["problems"] == []
        # The convention as the file name states it (Stone_Path_007_normal says nothing: null).
        stated = None if name == "StonePath007" else entry["normal_convention"]
        assert m["normal_convention"] == stated, name
    assert found["Metal009"]["normal_convention"] == "directx"  # ambientCG's plain _Normal
    assert set(found["large_castle_door"]["files"]) >= {"ao", "roughness", "metalness"}
    assert found["Chainmail004"]["files"]["opacity"] == "Chainmail004/Chainmail004_1K_Opacity.jpg"

    text = run_bcf("batch", library, "--list")
    assert text.returncode == 0 and "21 materials (21 complete)" in text.stdout
    assert "normal     Metal009/Metal009_2K_Normal.jpg" in text.stdout


def test_batch_compresses_all_then_skips_then_redoes_only_what_changed(library: Path, tmp_path: Path) -> None:
    assets = tmp_path / "assets"
    shutil.copytree(library, assets)
    out = tmp_path / "out"

    first = run_bcf("batch", assets, "-o", out, *TINY, "-j", "2", timeout=600)
    assert first.returncode == 0, first.stdout + first.stderr
    assert set(statuses(out).values()) == {"compressed"} and len(statuses(out)) == 21
    for name in NAMES:  # one bcf compress folder per material, mirroring the input tree
        assert load_export(out / name).manifest.material.width == SIZE
    items = summary(out)["items"]
    assert all(i["psnr"] > 10 and i["size_bytes"] > 0 for i in items)
    assert "21 materials: 21 compressed" in first.stdout
    assert "started Metal009" in first.stderr and "compressed Metal009: " in first.stderr  # progress lines
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("report.json")}

    second = run_bcf("batch", assets, "-o", out, *TINY, "-q")
    assert second.returncode == 0, second.stderr
    assert set(statuses(out).values()) == {"skipped"}
    assert {p: p.stat().st_mtime_ns for p in out.rglob("report.json")} == stamps

    # New content in one input: only that material is compressed again.
    albedo = assets / "plywood" / NAMES["plywood"]["albedo"]
    _write(albedo, _pixels("albedo", 99))
    # A truncated file breaks another one: it fails, the rest are untouched.
    broken = assets / "Rock015" / NAMES["Rock015"]["roughness"]
    broken.write_bytes(broken.read_bytes()[:200])
    third = run_bcf("batch", assets, "-o", out, *TINY, "-q")
    assert third.returncode == 1, third.stderr
    result = statuses(out)
    assert result.pop("plywood") == "compressed" and result.pop("Rock015") == "failed"
    assert set(result.values()) == {"skipped"}
    failure = next(i for i in summary(out)["items"] if i["material"] == "Rock015")
    assert "Rock015_1K-JPG_Roughness.jpg" in failure["error"]
    assert "Rock015_1K-JPG_Roughness.jpg" in third.stdout  # the summary table names the problem

    forced = run_bcf("batch", assets, "-o", out, *TINY, "-q", "--force", timeout=600)
    assert forced.returncode == 1
    assert list(statuses(out).values()).count("compressed") == 20


def test_an_interrupted_batch_continues_where_it_stopped(library: Path, tmp_path: Path) -> None:
    assets = tmp_path / "assets"
    for name in ("Bricks075B", "Chainmail004", "Metal009", "plywood"):  # a few: the rerun trains them all
        shutil.copytree(library / name, assets / name)
    out = tmp_path / "out"
    slow = ["--preset", "fast", "--phase1-iterations", "300", "--phase2-iterations", "300", "--batch-size", "1024"]
    process = subprocess.Popen([*BCF, "batch", str(assets), "-o", str(out), *slow, "-q"], env=ONE_THREAD_ENV,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint)
    deadline = time.monotonic() + 300
    finished = lambda: [p for p in out.glob("*/manifest.json") if not p.parent.name.startswith(".")]  # noqa: E731
    while not finished() and time.monotonic() < deadline:  # staging folders are hidden: wait for a result
        time.sleep(0.2)
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr
    first = statuses(out)
    done = {name for name, status in first.items() if status == "compressed"}
    assert done and "interrupted" in first.values() and "failed" not in first.values()
    assert "run the same command again to continue" in stderr
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no staging folder left behind

    again = run_bcf("batch", assets, "-o", out, *slow, "-q", timeout=900)
    assert again.returncode == 0, again.stderr
    second = statuses(out)
    assert {name for name, status in second.items() if status == "skipped"} == done


def test_submit_sends_materials_to_the_service_and_downloads_the_results(tmp_path: Path) -> None:
    assets = tmp_path / "assets"
    subset = ("Metal009", "denim_fabric_02", "large_castle_door")
    build_library(tmp_path / "all")
    assets.mkdir()
    for name in subset:
        (tmp_path / "all" / name).rename(assets / name)
    (tmp_path / "service").mkdir()
    environment = BcfEnvironment(tmp_path / "service", api_tokens="t0k3n")
    server = environment.serve(workers=1)
    try:
        out = tmp_path / "out"
        env = {**ONE_THREAD_ENV, "BCF_TOKEN": "t0k3n"}
        result = subprocess.run([*BCF, "batch", str(assets), "-o", str(out), "--submit", server.url, *TINY],
                                env=env, capture_output=True, text=True, timeout=300)
        assert result.returncode == 0, result.stdout + result.stderr
        items = summary(out)["items"]
        assert {i["material"]: i["status"] for i in items} == {name: "compressed" for name in subset}
        assert all(i["job_id"] for i in items) and summary(out)["mode"] == "submit"
        for name in subset:
            loaded = load_export(out / name)
            assert loaded.manifest.material.normal_convention == ("directx" if name == "Metal009" else "opengl")
        jobs = server.client.get("/v1/jobs").json()
        assert jobs["total"] == 3 and {j["state"] for j in jobs["jobs"]} == {"succeeded"}

        again = subprocess.run([*BCF, "batch", str(assets), "-o", str(out), "--submit", server.url, *TINY, "-q"],
                               env=env, capture_output=True, text=True, timeout=300)
        assert again.returncode == 0 and set(statuses(out).values()) == {"skipped"}
        wrong = subprocess.run([*BCF, "batch", str(assets), "-o", str(tmp_path / "o2"), "--submit", server.url,
                                "--token", "nope", *TINY], env=ONE_THREAD_ENV, capture_output=True, text=True,
                               timeout=120)
        assert wrong.returncode == 2 and "token" in wrong.stderr
    finally:
        server.stop()


def test_a_material_folder_with_material_subfolders_keeps_both_results_apart() -> None:
    def found(output: str) -> FoundMaterial:
        return FoundMaterial(material=output, dir=output, output=output, files={}, normal_convention=None,
                             resolution=None, notes=[], problems=[])

    names = _output_names([found("."), found("a"), found("a/b"), found("c")], "library")
    assert names == ["library", "a/a", "a/b", "c"]


def test_user_errors_exit_2(tmp_path: Path) -> None:
    missing = run_bcf("batch", tmp_path / "nope", "-o", tmp_path / "out")
    assert missing.returncode == 2 and "no such folder" in missing.stderr
    empty = run_bcf("batch", tmp_path, "-o", tmp_path / "out")
    assert empty.returncode == 2 and "no texture sets found" in empty.stderr
    no_output = run_bcf("batch", tmp_path)
    assert no_output.returncode == 2 and "-o OUT_DIR is required" in no_output.stderr


def test_the_terminal_display_redraws_overall_and_per_material_lines() -> None:
    import io

    from bcf.batch_cli import BatchProgress
    from bcf.jobs.batch import BatchItem, MaterialEvent
    from bcf.core.fit.training import TrainingProgress

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    screen = Terminal()
    display = BatchProgress(total=2, jobs=1, stream=screen)
    display(MaterialEvent("wood", "started"))
    display(MaterialEvent("wood", "progress", TrainingProgress(2, 150, 300, 31.5, 50.0, 3.0, 9.0)))
    display(MaterialEvent("wood", "progress", stage="evaluating the exported files"))
    assert "  wood: evaluating the exported files" in screen.getvalue()
    done = BatchItem(material="wood", dir="wood", output="wood", status="compressed", psnr=31.9, size_bytes=2048,
                     seconds=12.0)
    display(MaterialEvent("wood", "finished", item=done))
    text = screen.getvalue()
    assert "  wood: starting" in text and "batch: 0/2 done, 1 running" in text
    assert "\x1b[2F\x1b[J" in text  # the two-line block is redrawn in place
    assert "batch: 1/2 done, 0 running" in text and "ETA 0:00:12" in text  # one compressed in 12 s, one to go
