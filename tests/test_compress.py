"""The neural-material pipeline end to end on real files: `training.fit` -> `export.write_export` checked bit for bit
against three BC6H decoders, `compress.compress_material` (report.json, sizes, quality), and the `bcf compress`,
`bcf decode` and `bcf info` commands in a subprocess (outputs, user errors, Ctrl-C).

Inputs are tests/data/chainmail_128 and 128 px crops of examples/sample written into tmp_path; schedules are tiny
(a few hundred iterations) so the whole file runs in about a minute and a half on two cores. Each material is
compressed once per module and shared by the tests that read its output.
"""

from __future__ import annotations

import json
import math
import shutil
import signal
import subprocess
import threading
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from bcf.core import REPORT_FILE, decoded_file_names
from bcf.core import load_export
from bcf.core.codec import bc6h
from bcf.core import pipeline as compress
from bcf.core.codec import containers
from bcf.core.codec.textures import mode_histogram
from bcf.core.export import artifacts as export
from bcf.core.report import html as html_report
from bcf.core.report import metrics
from bcf.core.fit import training
from bcf.core.material.texture_set import TextureSet, load_material
from bcf.core.options import CompressOptions, resolve_options
from bcf.core.report.report_json import Report, read_report
from bcf.core.fit.sampling import ReferenceMaterial, material_mip_count
from bcf_command import BCF, ONE_THREAD_ENV, default_sigint, run_bcf
from crafted_images import png_claiming
from reference_decoders import MesaBC6HDecoder, decode_with_mesa, decode_with_oiio

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "examples" / "sample"
CHAINMAIL = Path(__file__).resolve().parent / "data" / "chainmail_128"

# Small schedules: enough to clear the mean baseline by several dB on 128 px, seconds of CPU each.
OPTIONS = CompressOptions(preset="fast", phase1_iterations=150, phase2_iterations=150, batch_size=4096)
TINY = CompressOptions(preset="fast", phase1_iterations=30, phase2_iterations=30, batch_size=2048)
CLI_TINY = ("--preset", "fast", "--phase1-iterations", "30", "--phase2-iterations", "30", "--batch-size", "1024")

DDS_HEADER_BYTES = 148  # magic + DDS_HEADER + DDS_HEADER_DXT10
# PSNR all must beat the trivial per-channel mean by this much. Measured with OPTIONS: chainmail 27.5 dB against
# 19.4 dB (+8.1); the sample crop 31.1 dB against 27.5 dB (+3.6: its normal and ARM maps are smooth, so the mean
# already does well there).
MIN_GAIN_OVER_MEAN_DB = {"chainmail": 5.0, "sample": 2.0}
PNG16 = 65535.0


# ------------------------------------------------------------------------------------------------ helpers


def assert_user_error(result: subprocess.CompletedProcess[str], *named: object) -> None:
    """Exit 2, a single `bcf: error:` line on stderr naming every item of `named`, no traceback."""
    assert result.returncode == 2, (result.returncode, result.stdout, result.stderr)
    assert result.stderr.startswith("bcf: error:"), result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    assert result.stderr.count("\n") == 1, result.stderr
    for name in named:
        assert str(name) in result.stderr, (name, result.stderr)


def assert_not_created(output: Path) -> None:
    """`output` does not exist and no staging (`.OUT.partial-*`) or backup (`.OUT.old-*`) folder is left."""
    assert not output.exists(), sorted(output.rglob("*")) if output.is_dir() else output
    leftovers = [p.name for p in output.parent.iterdir() if p.name.startswith(f".{output.name}.")]
    assert leftovers == [], leftovers


def write_png(path: Path, pixels: np.ndarray) -> Path:
    """Write (h, w, c) values in [0, 1] as an 8-bit PNG with plain OpenImageIO."""
    pixels = np.asarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    data = np.ascontiguousarray(np.rint(np.clip(pixels, 0.0, 1.0) * 255.0).astype(np.uint8))
    height, width, channels = data.shape
    output = oiio.ImageOutput.create(str(path))
    assert output is not None, oiio.geterror()
    assert output.open(str(path), oiio.ImageSpec(width, height, channels, "uint8")), output.geterror()
    assert output.write_image(data), output.geterror()
    assert output.close()
    return path


def read_oiio(path: Path) -> np.ndarray:
    """All channels of an image file as float32, with plain OpenImageIO (integers normalised to [0, 1])."""
    image_input = oiio.ImageInput.open(str(path))
    assert image_input is not None, oiio.geterror()
    spec = image_input.spec()
    pixels = image_input.read_image(0, 0, 0, spec.nchannels, "float")
    image_input.close()
    return np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)


def image_size(path: Path) -> tuple[int, int]:
    image_input = oiio.ImageInput.open(str(path))
    assert image_input is not None, oiio.geterror()
    spec = image_input.spec()
    image_input.close()
    return spec.width, spec.height


@lru_cache(maxsize=None)
def sample_pixels(name: str) -> np.ndarray:
    """The 256x256 sample's albedo / normal_gl / arm as stored (float32 in [0, 1])."""
    return read_oiio(SAMPLE / f"{name}.png")


def write_sample_set(folder: Path, width: int = 128, height: int = 128, x: int = 0, y: int = 0,
                     skip: tuple[str, ...] = ()) -> Path:
    """albedo.png, normal_gl.png, arm.png: a width x height crop at (x, y) of the sample, in `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("albedo", "normal_gl", "arm"):
        if name not in skip:
            write_png(folder / f"{name}.png", sample_pixels(name)[y:y + height, x:x + width])
    return folder


def dig(data: Any, dotted: str) -> Any:
    """data["a"]["b"][0]... for "a.b.0"; KeyError / IndexError name the missing part."""
    for part in dotted.split("."):
        data = data[int(part)] if isinstance(data, list) else data[part]
    return data


def psnr(reference: np.ndarray, test: np.ndarray) -> float:
    mse = float(np.mean((reference.astype(np.float64) - test.astype(np.float64)) ** 2))
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.iterdir() if p.is_file())


# ----------------------------------------------------------------------------------------------- fixtures


class Compressed:
    """A material compressed by `compress_material` once per module: its texture set, folder and report."""

    def __init__(self, texture_set: TextureSet, folder: Path, report: Report):
        self.texture_set = texture_set
        self.folder = folder
        self.report = report
        self.json = json.loads((folder / REPORT_FILE).read_text())
        self.manifest = json.loads((folder / export.MANIFEST_FILE).read_text())


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def chainmail_set() -> TextureSet:
    return load_material(CHAINMAIL)


@pytest.fixture(scope="module")
def sample_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 128x128 crop of examples/sample (albedo.png, normal_gl.png, arm.png)."""
    return write_sample_set(tmp_path_factory.mktemp("sample") / "sample_128", x=64, y=32)


@pytest.fixture(scope="module")
def chainmail(chainmail_set: TextureSet, tmp_path_factory: pytest.TempPathFactory) -> Compressed:
    folder = tmp_path_factory.mktemp("chainmail") / "out"
    return Compressed(chainmail_set, folder, compress.compress_material(chainmail_set, OPTIONS, folder))


@pytest.fixture(scope="module")
def sample(sample_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Compressed:
    texture_set = load_material(sample_dir)
    folder = tmp_path_factory.mktemp("sample_out") / "out"
    return Compressed(texture_set, folder, compress.compress_material(texture_set, OPTIONS, folder))


@pytest.fixture(scope="module")
def decoded(chainmail: Compressed, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    """`bcf decode --all-mips --bits 16` of the chainmail export."""
    output = tmp_path_factory.mktemp("decoded") / "images"
    result = run_bcf("decode", chainmail.folder, "-o", output, "--all-mips", "--bits", "16")
    assert result.returncode == 0, result.stderr
    return output, result


# ------------------------------------------------------------------------------- 1. export bit-exactness


@pytest.mark.parametrize("block_mode", [10, 11])
def test_exported_features_equal_the_training_forward_pass_in_three_decoders(
        chainmail_set: TextureSet, tmp_path: Path, mesa: MesaBC6HDecoder, block_mode: int) -> None:
    """Every mip of every feature texture, decoded from the DDS file by bcf, OpenImageIO and Mesa, is exactly
    what the phase-2 forward pass used (BlockFeatures.level): what was trained is what ships."""
    resolved = resolve_options(CompressOptions(preset="fast", phase1_iterations=60, phase2_iterations=60,
                                               batch_size=4096, block_mode=block_mode))
    result = training.fit(chainmail_set, resolved)
    mips = material_mip_count(chainmail_set.width, chainmail_set.height)
    manifest = export.write_export(tmp_path, result.model, chainmail_set.source, mips, resolved)
    features = result.model.features
    assert len(features.specs) == len(manifest.feature_textures) == 4
    compared = 0
    for i, spec in enumerate(features.specs):
        path = tmp_path / export.feature_file(i)
        texture = containers.read_dds(path)
        assert (texture.width, texture.height, len(texture.levels), texture.signed) == \
            (spec.width, spec.height, spec.levels, False)
        assert path.stat().st_size == DDS_HEADER_BYTES + sum(level.nbytes for level in texture.levels)
        by_mesa = decode_with_mesa(texture, mesa)
        assert len(by_mesa) == spec.levels
        for level in range(spec.levels):
            w, h = spec.level_size(level)
            with torch.no_grad():
                trained = features.level(i, level).detach().cpu().numpy().transpose(1, 2, 0)  # (h, w, 3) float32
            assert trained.shape == (h, w, 3) and trained.dtype == np.float32
            as_half = trained.astype(np.float16)
            # The forward pass produces half values exactly (float32 holding a float16), so the bit patterns compare.
            assert np.array_equal(as_half.astype(np.float32), trained), f"T{i} level {level}: not half values"
            expected = as_half.view(np.uint16)
            ours = bc6h.decode_image(texture.levels[level], w, h, signed=False)
            by_oiio = decode_with_oiio(path, level)
            for name, decoded in (("bcf", ours), ("OpenImageIO", by_oiio), ("Mesa", by_mesa[level])):
                assert decoded.shape == (h, w, 3) and decoded.dtype == np.float16, (name, decoded.shape)
                differ = np.count_nonzero(decoded.view(np.uint16) != expected)
                assert differ == 0, f"T{i} level {level}: {differ} texel channels from {name} differ from training"
            compared += 1
    assert compared == sum(spec.levels for spec in features.specs)
    # The trained features are not degenerate (e.g. all one value): the comparison means something.
    level0 = features.level(0, 0).detach().cpu().numpy()
    assert np.unique(level0).size > 100


def test_centre_error_is_the_reports_measure(chainmail_set: TextureSet) -> None:
    """`training.centre_error`, which picks between phase 2's result and its start, is the mean over mips of the
    report's texel-centre MSE over all channels."""
    reference = ReferenceMaterial(chainmail_set.channels, "wrap")
    result = training.fit(chainmail_set, resolve_options(CompressOptions(preset="fast", phase2_iterations=0)))
    model = result.model.eval()
    scores = metrics.evaluate(model, reference)
    assert training.centre_error(model, reference) == pytest.approx(np.mean([m["mse"]["all"] for m in scores]),
                                                                    rel=1e-5)


def test_a_phase_2_that_ends_below_its_start_returns_the_start(chainmail_set: TextureSet) -> None:
    """Rates far too high wreck the blocks in a few steps: the fit returns its start (the transition's blocks),
    not the wreck; after a short random-start phase 1, whose blocks start far from the material, it keeps phase 2's
    result."""
    reference = ReferenceMaterial(chainmail_set.channels, "wrap")
    wrecked = training.fit(chainmail_set, resolve_options(CompressOptions(
        preset="fast", phase2_iterations=20, batch_size=4096, lr_features_phase2=0.5, lr_mlp_phase2=0.5)))
    assert wrecked.start_kept
    assert training.centre_error(wrecked.model, reference) == training.centre_error(wrecked.naive_model, reference)
    assert wrecked.model is not wrecked.naive_model
    polished = training.fit(chainmail_set, resolve_options(CompressOptions(
        preset="fast", init="random", phase1_iterations=150, phase2_iterations=150, batch_size=4096)))
    assert not polished.start_kept
    assert training.centre_error(polished.model, reference) < training.centre_error(polished.naive_model, reference)


# ----------------------------------------------------------------------------------- 2. report.json


REQUIRED_KEYS = (
    "aggregate.psnr.all", "aggregate.ssim.all", "size.total_bytes", "size.features_bytes", "size.weights_bytes",
    "size.files_bytes", "timing.phase1_s", "timing.phase2_s", "models.trained_fp32.psnr.all",
    "models.phase1_unconstrained.psnr.all", "jittered.aggregate.psnr.all", "mean_baseline.psnr.all",
)
GROUP_NAMES = ("albedo", "normal", "arm", "all")


@pytest.mark.parametrize("which", ["chainmail", "sample"])
def test_report_has_every_field_and_true_sizes(which: str, request: pytest.FixtureRequest) -> None:
    compressed: Compressed = request.getfixturevalue(which)
    folder, data, manifest = compressed.folder, compressed.json, compressed.manifest
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        [export.feature_file(i) for i in range(4)] + [export.DECODER_FILE, export.MANIFEST_FILE, REPORT_FILE,
                                                    html_report.HTML_REPORT_FILE])
    for key in REQUIRED_KEYS:
        value = dig(data, key)
        assert isinstance(value, (int, float)) and math.isfinite(value), (key, value)
    for group in GROUP_NAMES:
        for metric in ("psnr", "ssim"):
            assert math.isfinite(dig(data, f"aggregate.{metric}.{group}"))
    assert data["timing"]["phase1_s"] > 0 and data["timing"]["phase2_s"] > 0
    assert isinstance(data["start_kept"], bool)

    # per mip: one entry per material mip, in order, with every group's PSNR and SSIM
    assert len(data["per_mip"]) == manifest["mips"] == material_mip_count(manifest["width"], manifest["height"])
    for m, entry in enumerate(data["per_mip"]):
        assert entry["mip"] == m
        assert (entry["width"], entry["height"]) == (manifest["width"] >> m, manifest["height"] >> m)
        for group in GROUP_NAMES:
            assert math.isfinite(entry["psnr"][group]) and -1.0 <= entry["ssim"][group] <= 1.0, (m, group)

    # sizes are those of the files on disk
    dds_payload = sum((folder / export.feature_file(i)).stat().st_size - DDS_HEADER_BYTES for i in range(4))
    size = data["size"]
    assert size["features_bytes"] == dds_payload
    assert size["features_bytes"] == sum(t["bytes"] for t in manifest["feature_textures"])
    assert size["weights_bytes"] == (folder / export.DECODER_FILE).stat().st_size == manifest["decoder"]["bytes"]
    assert size["total_bytes"] == size["features_bytes"] + size["weights_bytes"]
    assert size["files_bytes"] == folder_bytes(folder)
    assert size["bits_per_texel"] == pytest.approx(size["total_bytes"] * 8 / (manifest["width"] * manifest["height"]))
    # the file is the pydantic model the library returned
    assert Report.model_validate(data) == compressed.report == read_report(folder)


@pytest.mark.parametrize("which", ["chainmail", "sample"])
def test_quality_beats_mean_baseline_and_export_costs_nothing(which: str, request: pytest.FixtureRequest) -> None:
    data = request.getfixturevalue(which).json
    ours, baseline = data["aggregate"]["psnr"]["all"], data["mean_baseline"]["psnr"]["all"]
    print(f"{which}: PSNR all {ours:.2f} dB, per-channel mean {baseline:.2f} dB, "
          f"SSIM all {data['aggregate']['ssim']['all']:.4f} vs {data['mean_baseline']['ssim']['all']:.4f}")
    assert ours >= baseline + MIN_GAIN_OVER_MEAN_DB[which], (ours, baseline)
    assert data["aggregate"]["ssim"]["all"] > data["mean_baseline"]["ssim"]["all"] + 0.02
    # fp16 weights and the exported blocks (bit-exact) cost almost nothing against the fp32 training model
    assert data["models"]["exported"]["psnr"]["all"] == pytest.approx(ours, abs=1e-9)
    assert abs(ours - data["models"]["trained_fp32"]["psnr"]["all"]) < 0.1
    # every mip is reconstructed usefully, not just on average
    for entry in data["per_mip"]:
        assert entry["psnr"]["all"] > baseline, entry


# ------------------------------------------------------------------------------------------- 3. decode


def test_decode_writes_every_mip_at_its_size(decoded: tuple[Path, subprocess.CompletedProcess[str]],
                                             chainmail: Compressed) -> None:
    output, result = decoded
    mips = chainmail.manifest["mips"]
    expected = {decoded_file_names(m, ".png")[n] for m in range(mips) for n in ("albedo", "normal", "arm")}
    assert {"albedo.png", "normal.png", "arm.png", "albedo_mip1.png", f"arm_mip{mips - 1}.png"} <= expected
    assert {p.name for p in output.iterdir()} == expected
    for m in range(mips):
        for name in decoded_file_names(m, ".png").values():
            path = output / name
            assert image_size(path) == (128 >> m, 128 >> m), name
            spec = oiio.ImageInput.open(str(path))
            assert spec.spec().nchannels == 3 and str(spec.spec().format) == "uint16", name
            spec.close()
            assert f"wrote {path}" in result.stdout


def test_decoded_images_score_what_the_report_says(decoded: tuple[Path, subprocess.CompletedProcess[str]],
                                                   chainmail: Compressed) -> None:
    """The decoded PNGs (16 bit) against the reference mips give the per-mip PSNRs of report.json."""
    output, _ = decoded
    reference = ReferenceMaterial(chainmail.texture_set.channels, "wrap")
    for m, entry in enumerate(chainmail.json["per_mip"]):
        ref = reference.mip(m).numpy().transpose(1, 2, 0)  # (h, w, 8)
        names = decoded_file_names(m, ".png")
        albedo, normal, arm = (read_oiio(output / names[n]) for n in ("albedo", "normal", "arm"))
        test = np.concatenate([albedo, normal[..., :2], arm], axis=-1)
        measured = {"albedo": psnr(ref[..., 0:3], test[..., 0:3]), "normal": psnr(ref[..., 3:5], test[..., 3:5]),
                    "arm": psnr(ref[..., 5:8], test[..., 5:8]), "all": psnr(ref, test)}
        for group, value in measured.items():
            assert abs(value - entry["psnr"][group]) < 0.05, (m, group, value, entry["psnr"][group])


def test_decoded_normal_blue_is_rebuilt_z(decoded: tuple[Path, subprocess.CompletedProcess[str]],
                                          chainmail: Compressed) -> None:
    output, _ = decoded
    for m in range(chainmail.manifest["mips"]):
        normal = read_oiio(output / decoded_file_names(m, ".png")["normal"]).astype(np.float64)
        xy = normal[..., :2] * 2.0 - 1.0
        z = np.sqrt(np.clip(1.0 - (xy**2).sum(-1), 0.0, 1.0))
        # x, y were quantised to 16 bits before we read them: |dx|, |dy| <= 1 / 65535, so 1 - x^2 - y^2 moves by
        # at most eps; sqrt moves by at most min(eps / z, sqrt(eps)). Blue itself is rounded by half a step.
        eps = 2.0 * np.abs(xy).sum(-1) / PNG16 + 2.0 / PNG16**2
        slack = 0.5 * np.minimum(eps / np.maximum(z, 1e-12), np.sqrt(eps)) + 0.5 / PNG16 + 1e-7
        error = np.abs(normal[..., 2] - (z + 1.0) / 2.0)
        assert np.all(error <= slack), (m, float(error.max()))
        # and in practice it is the 16-bit rounding: almost every texel within one step
        assert np.mean(error <= 1.0 / PNG16) > 0.99, m
        assert normal[..., 2].min() >= 0.5 - 1e-6  # z >= 0: a tangent-space normal points out of the surface


def test_decode_exr_and_missing_mip(chainmail: Compressed, decoded: tuple[Path, subprocess.CompletedProcess[str]],
                                    tmp_path: Path) -> None:
    exr = tmp_path / "exr"
    result = run_bcf("decode", chainmail.folder, "-o", exr, "--format", "exr", "--mip", "1")
    assert result.returncode == 0, result.stderr
    assert {p.name for p in exr.iterdir()} == set(decoded_file_names(1, ".exr").values()) == \
        {"albedo_mip1.exr", "normal_mip1.exr", "arm_mip1.exr"}
    png_dir, _ = decoded
    for name in ("albedo", "normal", "arm"):
        half = read_oiio(exr / f"{name}_mip1.exr")
        assert half.shape == (64, 64, 3)
        png = read_oiio(png_dir / f"{name}_mip1.png")
        assert np.max(np.abs(half - png)) < 1e-3, name  # half vs 16-bit rounding of the same values

    missing = tmp_path / "missing"
    result = run_bcf("decode", chainmail.folder, "-o", missing, "--mip", "99")
    assert_user_error(result, "mip 99", chainmail.folder)
    assert not missing.exists()


# ------------------------------------------------------------------------------------ 4. reproducibility


def test_same_seed_gives_identical_files_and_another_seed_does_not(chainmail_set: TextureSet, tmp_path: Path) -> None:
    def run(seed: int, name: str) -> dict[str, bytes]:
        folder = tmp_path / name
        compress.compress_material(chainmail_set, TINY.model_copy(update={"seed": seed}), folder)
        return {f: (folder / f).read_bytes() for f in [export.feature_file(i) for i in range(4)] + [export.DECODER_FILE]}

    first, again, other = run(7, "a"), run(7, "b"), run(8, "c")
    for name in first:
        assert first[name] == again[name], f"{name} differs between two runs with seed 7"
    differing = [name for name in first if first[name] != other[name]]
    assert export.DECODER_FILE in differing and len(differing) >= 4, differing


# ------------------------------------------------------------------------------- 5. non-square, clamp


def test_non_square_material_with_clamp_addressing(tmp_path: Path) -> None:
    material = write_sample_set(tmp_path / "wide", width=128, height=64, x=32, y=100)
    output = tmp_path / "out"
    result = run_bcf("compress", material, "-o", output, "--address", "clamp", *CLI_TINY, "-q")
    assert result.returncode == 0, result.stderr
    manifest = json.loads((output / export.MANIFEST_FILE).read_text())
    assert (manifest["width"], manifest["height"], manifest["mips"]) == (128, 64, 5)
    assert manifest["address"] == "clamp" and manifest["options"]["address"] == "clamp"
    assert read_report(output).options.address == "clamp"
    for i, texture in enumerate(manifest["feature_textures"]):
        assert texture["width"] == 2 * texture["height"], texture
        assert containers.read_dds(output / texture["file"]).width == texture["width"]
    assert [(m["width"], m["height"]) for m in json.loads((output / REPORT_FILE).read_text())["per_mip"]] \
        == [(128 >> m, 64 >> m) for m in range(5)]

    images = tmp_path / "images"
    result = run_bcf("decode", output, "-o", images, "--all-mips")
    assert result.returncode == 0, result.stderr
    for m in range(5):
        for name in decoded_file_names(m, ".png").values():
            assert image_size(images / name) == (128 >> m, 64 >> m), name


# ------------------------------------------------------------------------------------ 6. bad input


def _case_empty(tmp: Path) -> tuple[list[object], list[object]]:
    (tmp / "mat").mkdir()
    return [tmp / "mat"], [tmp / "mat", "no files"]


def _case_missing_normal(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat", skip=("normal_gl",))
    return [folder], [folder, "missing normal"]


def _case_two_albedos(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat")
    shutil.copy(folder / "albedo.png", folder / "basecolor.png")
    return [folder], ["albedo.png", "basecolor.png", "albedo map"]


def _case_mismatched_sizes(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat")
    write_png(folder / "normal_gl.png", sample_pixels("normal_gl")[:64, :64])
    return [folder], [folder / "normal_gl.png", "64x64", "128x128", "differ in size"]


def _case_not_power_of_two(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat", width=96, height=96)
    return [folder], [folder / "albedo.png", "96x96", "power of two"]


def _case_too_small(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat", width=32, height=32)
    return [folder], [folder / "albedo.png", "32x32", "at least 64"]


def _case_unreadable(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat")
    (folder / "albedo.png").write_bytes(bytes(range(256)) * 8)
    return [folder], [folder / "albedo.png", "cannot read"]


def _case_grey_albedo(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat")
    write_png(folder / "albedo.png", sample_pixels("albedo")[:128, :128, 0])
    return [folder], [folder / "albedo.png", "albedo needs 3 channels", "found 1"]


def _case_arm_and_roughness(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat")
    rough = write_png(folder / "rough.png", sample_pixels("arm")[:128, :128, 1])
    args = ["--albedo", folder / "albedo.png", "--normal", folder / "normal_gl.png", "--arm", folder / "arm.png",
            "--roughness", rough]
    return args, [folder / "arm.png", "--arm cannot be combined with --roughness"]


def _case_pixel_bomb(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat")
    (folder / "albedo.png").write_bytes(png_claiming(16384, 16384))  # 32 KiB claiming 768 MiB of pixels
    return [folder], [folder / "albedo.png", "16384x16384 is 268,435,456 pixels", "limit of 67,108,864"]


def _case_over_max_pixels(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat")
    return [folder, "--max-pixels", "4096"], [folder / "albedo.png", "128x128 is 16,384 pixels", "limit of 4,096"]


def _case_over_memory_budget(tmp: Path) -> tuple[list[object], list[object]]:
    folder = write_sample_set(tmp / "mat")
    return [folder, "--memory-budget-mb", "64"], ["128x128 material", "more than the budget of 0.1 GiB",
                                                  "--memory-budget-mb"]


def _case_no_such_folder(tmp: Path) -> tuple[list[object], list[object]]:
    return [tmp / "nope"], [tmp / "nope", "no such folder"]


BAD_INPUTS: dict[str, Callable[[Path], tuple[list[object], list[object]]]] = {
    "empty folder": _case_empty,
    "missing normal": _case_missing_normal,
    "two albedo candidates": _case_two_albedos,
    "mismatched sizes": _case_mismatched_sizes,
    "non-power-of-two": _case_not_power_of_two,
    "32x32": _case_too_small,
    "unreadable png": _case_unreadable,
    "1-channel albedo": _case_grey_albedo,
    "--arm with --roughness": _case_arm_and_roughness,
    "nonexistent folder": _case_no_such_folder,
    "decompression bomb": _case_pixel_bomb,
    "over --max-pixels": _case_over_max_pixels,
    "over --memory-budget-mb": _case_over_memory_budget,
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_a_user_error_and_writes_nothing(case: str, tmp_path: Path) -> None:
    args, named = BAD_INPUTS[case](tmp_path)
    output = tmp_path / "out"
    result = run_bcf("compress", *args, "-o", output, *CLI_TINY, "-q")
    assert_user_error(result, *named)
    assert_not_created(output)


@pytest.mark.parametrize("where", ["inside a file", "in /proc"])
def test_an_output_that_cannot_be_written_is_refused_before_training(where: str, sample_dir: Path,
                                                                     tmp_path: Path) -> None:
    """Refused at once, not after the training: with a million phase-2 iterations asked for, a check made after
    the fit would run into the timeout. (/proc refuses new folders even to root, who may write anywhere else.)"""
    if where == "inside a file":
        (tmp_path / "notes.txt").write_text("a file\n")
        output = tmp_path / "notes.txt" / "out"
    else:
        output = Path("/proc") / f"bcf-test-{tmp_path.name}" / "out"
    result = run_bcf("compress", sample_dir, "-o", output, "--preset", "fast", "--phase2-iterations", "1000000",
                     "-q", timeout=60)
    assert_user_error(result, output, "cannot write the output here")
    assert not output.exists()


def test_existing_output_needs_force(sample_dir: Path, tmp_path: Path) -> None:
    output = tmp_path / "out"
    output.mkdir()
    (output / "keep.txt").write_text("precious\n")
    result = run_bcf("compress", sample_dir, "-o", output, *CLI_TINY, "-q")
    assert_user_error(result, output, "--force")
    assert [p.name for p in output.iterdir()] == ["keep.txt"]
    assert (output / "keep.txt").read_text() == "precious\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]

    result = run_bcf("compress", sample_dir, "-o", output, *CLI_TINY, "-q", "--force")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in output.iterdir()) == sorted(
        [export.feature_file(i) for i in range(4)] + [export.DECODER_FILE, export.MANIFEST_FILE, REPORT_FILE,
                                                    html_report.HTML_REPORT_FILE])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no .out.old-* or .out.partial-* left
    load_export(output)


# ------------------------------------------------------------------------------------------- 7. Ctrl-C


def test_ctrl_c_exits_130_and_writes_nothing(sample_dir: Path, tmp_path: Path) -> None:
    output = tmp_path / "out"
    process = subprocess.Popen([*BCF, "compress", str(sample_dir), "-o", str(output), "--preset", "fast",
                                "--phase1-iterations", "1000000", "--phase2-iterations", "10", "--batch-size", "1024"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ONE_THREAD_ENV,
                               preexec_fn=default_sigint)
    watchdog = threading.Timer(120, process.kill)  # never hang the suite if the progress line never comes
    watchdog.start()
    try:
        seen = []
        assert process.stderr is not None
        for line in process.stderr:
            seen.append(line)
            if "phase 1" in line:
                break
        assert any("phase 1" in line for line in seen), ("no progress line", seen)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        watchdog.cancel()
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 130, (process.returncode, stdout, stderr)
    assert "interrupted" in stderr, stderr
    assert "Traceback" not in stderr, stderr
    assert_not_created(output)


# ---------------------------------------------------------------------------------- 8. info, bad exports


def test_info_describes_the_export(chainmail: Compressed) -> None:
    result = run_bcf("info", chainmail.folder)
    assert result.returncode == 0, result.stderr
    for i, texture in enumerate(chainmail.manifest["feature_textures"]):
        assert f"features_{i}.dds: BC6H_UF16 {texture['width']}x{texture['height']}, {texture['mips']} mips" \
            in result.stdout, result.stdout
    assert "MLP 12-16-8" in result.stdout and "decoder.bin" in result.stdout
    assert "PSNR all" in result.stdout and "SSIM all" in result.stdout
    assert f"{chainmail.json['aggregate']['psnr']['all']:.2f}" in result.stdout
    for m in range(chainmail.manifest["mips"]):
        size = 128 >> m
        assert f"{size}x{size}" in result.stdout


def test_decode_refuses_a_modified_feature_file(chainmail: Compressed, tmp_path: Path) -> None:
    folder = tmp_path / "copy"
    shutil.copytree(chainmail.folder, folder)
    path = folder / "features_0.dds"
    data = bytearray(path.read_bytes())
    data[DDS_HEADER_BYTES + 37] ^= 0x01
    path.write_bytes(bytes(data))
    output = tmp_path / "images"
    result = run_bcf("decode", folder, "-o", output)
    assert_user_error(result, "features_0.dds")
    assert not output.exists() or not any(output.iterdir())


MANIFEST_EDITS: dict[str, tuple[Callable[[dict[str, Any]], None], tuple[str, ...]]] = {
    "a 65536² material": (lambda m: m.update(width=65536, height=65536), ("width", "less than or equal to 16384")),
    "a negative size": (lambda m: m["feature_textures"][0].update(width=-4), ("feature_textures.0.width",)),
    "a file outside the folder": (lambda m: m["feature_textures"][0].update(file="/etc/hostname"),
                                  ("'/etc/hostname' is not a file name inside the export folder",)),
    "a file above the folder": (lambda m: m["decoder"].update(file="../decoder.bin"), ("decoder.file",)),
    "no layers": (lambda m: m["decoder"].update(layers=[]), ("decoder.layers",)),
    "a huge layer": (lambda m: m["decoder"]["layers"][0].update(inputs=10**9), ("decoder.layers.0.inputs",)),
    "a layer of the wrong width": (lambda m: m["decoder"]["layers"][0].update(inputs=11), ("12-N-8",)),
    "MLP inputs out of range": (lambda m: m["feature_textures"][0].update(mlp_inputs=[0, 1, 99]),
                                ("mlp_inputs",)),
    "a million mips": (lambda m: m.update(mips=10**6), ("mips",)),
    "no feature textures": (lambda m: m.update(feature_textures=[]), ("feature_textures",)),
    "a NaN LOD bias": (lambda m: m["feature_textures"][0].update(lod_bias=float("nan")), ("lod_bias",)),
    "weights past the end of decoder.bin": (lambda m: m["decoder"]["layers"][1].update(weight_offset=10**6),
                                            ("decoder.bin", "fp16 values")),
    "a texture size other than its DDS header's": (lambda m: m["feature_textures"][1].update(bytes=16),
                                                   ("features_1.dds", "16 bytes")),
    "a decoder size other than its file's": (lambda m: m["decoder"].update(bytes=2), ("decoder.bin", "says 2")),
}


@pytest.mark.parametrize("command", ["decode", "info"])
@pytest.mark.parametrize("case", list(MANIFEST_EDITS))
def test_an_edited_manifest_is_one_error_line(case: str, command: str, chainmail: Compressed,
                                             tmp_path: Path) -> None:
    """A manifest edited by hand or by an attacker: exit 2 and one `bcf: error:` line naming the problem, before
    any large allocation, and no file outside the folder read (issue 16, case 8)."""
    folder = tmp_path / "copy"
    shutil.copytree(chainmail.folder, folder)
    edit, named = MANIFEST_EDITS[case]
    manifest = json.loads((folder / export.MANIFEST_FILE).read_text())
    edit(manifest)
    (folder / export.MANIFEST_FILE).write_text(json.dumps(manifest))
    output = tmp_path / "images"
    result = run_bcf(command, folder, *(["-o", output] if command == "decode" else []), timeout=60)
    assert_user_error(result, *named)
    assert not output.exists() or not any(output.iterdir())


def test_info_checks_every_file_against_the_manifest(chainmail: Compressed, tmp_path: Path) -> None:
    folder = tmp_path / "copy"
    shutil.copytree(chainmail.folder, folder)
    assert "the 5 files the manifest lists match their SHA-256 and sizes" in run_bcf("info", folder).stdout
    with (folder / export.DECODER_FILE).open("ab") as stream:
        stream.write(b"\0")
    assert_user_error(run_bcf("info", folder), "decoder.bin", "sha256")


def test_decode_needs_a_manifest(chainmail: Compressed, tmp_path: Path) -> None:
    folder = tmp_path / "copy"
    shutil.copytree(chainmail.folder, folder)
    (folder / export.MANIFEST_FILE).unlink()
    output = tmp_path / "images"
    result = run_bcf("decode", folder, "-o", output)
    assert_user_error(result, export.MANIFEST_FILE, folder)
    assert not output.exists()


# -------------------------------------------------------------------------------------- 9. explicit files


def test_compress_explicit_files(sample_dir: Path, tmp_path: Path) -> None:
    output = tmp_path / "out"
    albedo, normal, arm = sample_dir / "albedo.png", sample_dir / "normal_gl.png", sample_dir / "arm.png"
    result = run_bcf("compress", "--albedo", albedo, "--normal", normal, "--arm", arm, "-o", output, *CLI_TINY, "-q")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("material albedo: 128x128"), result.stdout
    assert "normal convention opengl" in lines[0] and "ARM packed" in lines[0]
    for role, path in (("albedo", albedo), ("normal", normal), ("arm", arm)):
        assert any(line.split()[:2] == [role, path.name] for line in lines), (role, result.stdout)
    assert f"wrote {output}" in result.stdout
    manifest = export.read_manifest(output)
    assert {f.role: f.name for f in manifest.material.files} == {"albedo": "albedo.png", "normal": "normal_gl.png",
                                                                 "arm": "arm.png"}
    assert manifest.material.arm_packed and manifest.material.name == "albedo"
    assert (manifest.options.phase1_iterations, manifest.options.phase2_iterations) == (30, 30)


def test_block_mode_flag_takes_mode_numbers_and_auto(sample_dir: Path, tmp_path: Path) -> None:
    """`--block-mode 10` is mode 10 (a number on the command line, though the option also takes `auto`), and the
    exported texture then holds mode-10 blocks only."""
    output = tmp_path / "out"
    result = run_bcf("compress", sample_dir, "-o", output, *CLI_TINY, "--block-mode", "10", "-q")
    assert result.returncode == 0, result.stderr
    assert export.read_manifest(output).options.block_mode == 10
    texture = containers.read_dds(output / "features_0.dds")
    assert all(set(mode_histogram(level)) == {10} for level in texture.levels)


def test_random_start_without_phase_1_is_refused(sample_dir: Path, tmp_path: Path) -> None:
    """The fast and default presets skip phase 1, which only the principal-component start may do: a random
    start there is a user error, not a noise texture."""
    output = tmp_path / "out"
    result = run_bcf("compress", sample_dir, "-o", output, "--preset", "fast", "--init", "random", "-q")
    assert_user_error(result, "init random needs phase-1 iterations", "preset paper")
    assert_not_created(output)
