"""The `bcf` command line end to end (real files, the installed console script in a subprocess), plus unit
tests of the helpers it relies on: `images.mip_chain`, `images.read_rgb` and `bc6h_tools.mode_histogram`."""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

import bcf
from bcf.core.codec import bc6h
from bcf.core.codec import containers
from bcf.core.codec.textures import mode_histogram
from bcf.core.material.images import mip_chain, read_rgb
from bcf_command import run_bcf

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "examples" / "sample" / "albedo.png"


def assert_user_error(result: subprocess.CompletedProcess[str], *named: object) -> None:
    """Exit 2, a single `bcf: error:` line on stderr that names every item of `named`, no traceback."""
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert result.stderr.startswith("bcf: error:"), result.stderr
    assert "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1, result.stderr
    for name in named:
        assert str(name) in result.stderr, (name, result.stderr)


def files_under(folder: Path) -> set[Path]:
    return {p.relative_to(folder) for p in folder.rglob("*")}


# ------------------------------------------------------------------------------------------ basics


def test_version() -> None:
    result = run_bcf("--version")
    assert result.returncode == 0
    assert result.stdout == f"bcf {bcf.__version__}\n"


def test_module_entry_point_version() -> None:
    result = subprocess.run([sys.executable, "-m", "bcf", "--version"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0
    assert result.stdout == f"bcf {bcf.__version__}\n"


def test_help_lists_commands_with_descriptions() -> None:
    result = run_bcf("--help")
    assert result.returncode == 0
    for command in ("encode", "decode", "info"):
        assert re.search(rf"^\s+bc6h {command}\s+\S.*$", result.stdout, re.MULTILINE), result.stdout


# --------------------------------------------------------------------------------- encode / info / decode


@dataclass(frozen=True)
class Encoded:
    path: Path
    mode: int
    result: subprocess.CompletedProcess[str]


# One encode per container, shared by the tests below: every bcf run that touches the codec pays about
# 1.5 s of torch import. DDS is written in mode 10, KTX2 in mode 11, so both modes are covered too.
@pytest.fixture(scope="module", params=[("dds", 10), ("ktx2", 11)], ids=["dds-mode10", "ktx2-mode11"])
def encoded(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Encoded:
    extension, mode = request.param
    path = tmp_path_factory.mktemp("encode") / "nested" / "dir" / f"albedo.{extension}"  # parents get created
    result = run_bcf("bc6h", "encode", SAMPLE, "-o", path, "--mode", mode, "--verify")
    return Encoded(path, mode, result)


def test_encode_writes_file_and_verifies(encoded: Encoded) -> None:
    assert encoded.result.returncode == 0, encoded.result.stderr
    assert encoded.result.stderr == ""
    assert encoded.path.is_file()
    assert [p.name for p in encoded.path.parent.iterdir()] == [encoded.path.name]  # no temporary left behind
    rows = re.findall(r"^\s+(\d+)\s+(\d+x\d+)\s+([\d.]+|inf)\s+([\d.e+-]+)$", encoded.result.stdout, re.MULTILINE)
    assert [int(level) for level, *_ in rows] == list(range(9)), encoded.result.stdout
    assert rows[0][1] == "256x256" and rows[-1][1] == "1x1"
    psnr = [float(row[2]) for row in rows]
    assert min(psnr) > 25.0 and psnr[0] > 30.0, encoded.result.stdout


def test_info_reports_size_levels_and_single_mode(encoded: Encoded) -> None:
    result = run_bcf("bc6h", "info", encoded.path)
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert re.search(r"^container:\s+" + ("DDS" if encoded.path.suffix == ".dds" else "KTX2") + "$", out, re.M)
    assert re.search(r"^format:\s+BC6H_UF16$", out, re.MULTILINE)
    assert re.search(r"^size:\s+256x256$", out, re.MULTILINE)
    assert re.search(r"^levels:\s+9$", out, re.MULTILINE)
    modes = re.findall(r"^\s+mode (\d+): (\d+) blocks", out, re.MULTILINE)
    assert modes == [(str(encoded.mode), "4096")], out
    assert "reserved" not in out


def test_decode_matches_library_decode(encoded: Encoded, tmp_path: Path) -> None:
    # DDS -> EXR of level 0, KTX2 -> PNG of level 2: both outputs and both containers in two (slow) runs.
    extension, level = {".dds": (".exr", 0), ".ktx2": (".png", 2)}[encoded.path.suffix]
    out = tmp_path / f"decoded{extension}"
    result = run_bcf("bc6h", "decode", encoded.path, "-o", out, "--level", level)
    assert result.returncode == 0, result.stderr
    texture = containers.read_texture(encoded.path)
    width, height = texture.level_size(level)
    expected = bc6h.decode_image(texture.levels[level], width, height, texture.signed).astype(np.float32)
    got = read_rgb(out)
    assert got.shape == (height, width, 3)
    if extension == ".exr":
        np.testing.assert_array_equal(got, expected)  # half in, half out: bit exact
    else:
        # 16-bit PNG of the values clamped to [0, 1], rounded to nearest.
        np.testing.assert_allclose(got, np.clip(expected, 0, 1), rtol=0, atol=0.5 / 65535 + 1e-7)


# ------------------------------------------------------------------------------------------------ errors


@pytest.fixture
def truncated_dds(tmp_path: Path) -> Path:
    """A valid-looking DDS header whose level data is cut short (built in-process: no codec needed)."""
    blocks = np.zeros((2, 2, 16), dtype=np.uint8)
    full = tmp_path / "full.dds"
    containers.write_dds(full, containers.BC6HTexture(8, 8, False, (blocks,)))
    cut = tmp_path / "cut.dds"
    cut.write_bytes(full.read_bytes()[:-10])
    full.unlink()
    return cut


def _text_file(folder: Path, name: str) -> Path:
    path = folder / name
    path.write_text("this is not an image\n")
    return path


@pytest.mark.parametrize("case", [
    "encode-missing", "encode-text-as-image", "encode-text-with-png-name", "encode-unknown-extension",
    "encode-no-extension", "encode-too-many-levels", "info-missing", "info-truncated", "info-text",
    "decode-missing", "decode-truncated", "decode-unknown-extension", "decode-bad-level",
])
def test_user_errors_exit_2_and_write_nothing(case: str, tmp_path: Path, truncated_dds: Path) -> None:
    before = files_under(tmp_path)
    out_dir = tmp_path / "out"
    missing = tmp_path / "missing.png"
    valid_dds = tmp_path / "valid.dds"
    if case == "decode-bad-level":
        containers.write_dds(valid_dds, containers.BC6HTexture(4, 4, False, (np.zeros((1, 1, 16), np.uint8),)))
        before = files_under(tmp_path)
    args, named = {
        "encode-missing": (("encode", missing, "-o", out_dir / "a.dds"), [missing]),
        "encode-text-as-image": (("encode", _text_file(tmp_path, "notes.txt"), "-o", out_dir / "a.dds"),
                                 ["notes.txt"]),
        "encode-text-with-png-name": (("encode", _text_file(tmp_path, "fake.png"), "-o", out_dir / "a.dds"),
                                      ["fake.png"]),
        "encode-unknown-extension": (("encode", SAMPLE, "-o", out_dir / "a.bmp"), ["a.bmp", ".dds", ".ktx2"]),
        "encode-no-extension": (("encode", SAMPLE, "-o", out_dir / "a"), [out_dir / "a"]),
        "encode-too-many-levels": (("encode", SAMPLE, "-o", out_dir / "a.dds", "--levels", 10), [SAMPLE, "9"]),
        "info-missing": (("info", tmp_path / "missing.dds"), ["missing.dds"]),
        "info-truncated": (("info", truncated_dds), [truncated_dds, "truncated"]),
        "info-text": (("info", _text_file(tmp_path, "notes.dds")), ["notes.dds"]),
        "decode-missing": (("decode", tmp_path / "missing.dds", "-o", out_dir / "a.exr"), ["missing.dds"]),
        "decode-truncated": (("decode", truncated_dds, "-o", out_dir / "a.exr"), [truncated_dds, "truncated"]),
        "decode-unknown-extension": (("decode", truncated_dds, "-o", out_dir / "a.tif"), ["a.tif"]),
        "decode-bad-level": (("decode", valid_dds, "-o", out_dir / "a.exr", "--level", 1), [valid_dds, "0..0"]),
    }[case]
    before = before | {p.relative_to(tmp_path) for p in tmp_path.iterdir()}  # input files made above
    result = run_bcf("bc6h", *args)
    assert_user_error(result, *named)
    assert result.stdout == ""
    assert files_under(tmp_path) == before  # no output, no output folder, no temporary


@pytest.mark.parametrize("args, message", [
    (("--mode", "12"), "--mode"),
    (("--levels", "0"), "--levels"),
    (("--levels", "3", "--no-mips"), "not allowed"),
])
def test_bad_arguments_exit_2(args: tuple[str, ...], message: str, tmp_path: Path) -> None:
    result = run_bcf("bc6h", "encode", SAMPLE, "-o", tmp_path / "a.dds", *args)
    assert_user_error(result, message)
    assert not any(tmp_path.iterdir())


def test_missing_command_is_a_usage_error() -> None:
    assert_user_error(run_bcf("bc6h"), "bcf bc6h --help")


# ----------------------------------------------------------------------------------------------- mip_chain


@pytest.mark.parametrize("width, height, sizes", [
    (1024, 512, [(1024 >> i, max(1, 512 >> i)) for i in range(11)]),
    (20, 12, [(20, 12), (10, 6), (5, 3), (2, 1), (1, 1)]),
    (5, 3, [(5, 3), (2, 1), (1, 1)]),
])
def test_mip_chain_sizes(width: int, height: int, sizes: list[tuple[int, int]]) -> None:
    chain = mip_chain(np.zeros((height, width, 3), dtype=np.float32))
    assert [(level.shape[1], level.shape[0]) for level in chain] == sizes
    assert all(level.dtype == np.float32 and level.shape[2] == 3 for level in chain)
    assert len(chain) == containers.full_mip_count(width, height)
    assert [containers.mip_size(width, height, i) for i in range(len(chain))] == sizes


@pytest.mark.parametrize("shape", [(512, 1024), (12, 20), (3, 5), (7, 1)])
def test_mip_chain_constant_stays_constant(shape: tuple[int, int]) -> None:
    value = np.array([0.3, 1.7, 250.0], dtype=np.float32)
    for level in mip_chain(np.broadcast_to(value, (*shape, 3))):
        np.testing.assert_allclose(level, np.broadcast_to(value, level.shape), rtol=1e-6)


@pytest.mark.parametrize("shape", [(64, 128), (256, 256), (1, 32)])
def test_mip_chain_preserves_mean_for_power_of_two_sizes(shape: tuple[int, int]) -> None:
    image = np.random.default_rng(1).random((*shape, 3), dtype=np.float32) * 4.0
    mean = image.astype(np.float64).mean(axis=(0, 1))
    for level in mip_chain(image):
        np.testing.assert_allclose(level.astype(np.float64).mean(axis=(0, 1)), mean, rtol=1e-6)


def test_mip_chain_odd_rule_weights_by_coverage() -> None:
    # 5 -> 2: each output covers 2.5 texels: (a + b + c/2) / 2.5 and (c/2 + d + e) / 2.5.
    row = np.array([1.0, 2.0, 4.0, 8.0, 16.0], dtype=np.float32).reshape(1, 5, 1)
    level1 = mip_chain(row, levels=2)[1]
    np.testing.assert_allclose(level1[0, :, 0], [(1 + 2 + 2) / 2.5, (2 + 8 + 16) / 2.5], rtol=1e-6)
    # The rule keeps the mean for odd sizes too.
    image = np.random.default_rng(2).random((7, 13, 3))
    for level in mip_chain(image):
        np.testing.assert_allclose(level.mean(axis=(0, 1)), image.mean(axis=(0, 1)), rtol=1e-5)


def test_mip_chain_levels_argument() -> None:
    image = np.zeros((8, 8, 3), dtype=np.float32)
    assert len(mip_chain(image, levels=2)) == 2
    for bad in (0, 5):
        with pytest.raises(ValueError, match="mip levels"):
            mip_chain(image, levels=bad)


# ------------------------------------------------------------------------------------------------ helpers


@pytest.mark.parametrize("channels, expected", [
    (1, lambda p: np.repeat(p, 3, axis=2)),
    (2, lambda p: np.concatenate([p, np.zeros_like(p[..., :1])], axis=2)),
    (4, lambda p: p[..., :3]),
])
def test_read_rgb_channel_rules(tmp_path: Path, channels: int, expected) -> None:
    # PNG stores grey+alpha and RGBA unassociated; read_rgb must return the stored colour, not colour * alpha.
    pixels = np.random.default_rng(3).integers(0, 256, (4, 6, channels), dtype=np.uint8)
    path = tmp_path / "image.png"
    spec = oiio.ImageSpec(6, 4, channels, "uint8")
    spec.attribute("oiio:UnassociatedAlpha", 1)  # store the pixels as given, not un-premultiplied
    output = oiio.ImageOutput.create(str(path))
    assert output.open(str(path), spec)
    assert output.write_image(pixels)
    output.close()
    got = read_rgb(path)
    assert got.dtype == np.float32 and got.shape == (4, 6, 3)
    np.testing.assert_allclose(got, expected(pixels.astype(np.float32) / 255.0), atol=1e-7)


def test_mode_histogram_reads_the_mode_field_like_the_decoder() -> None:
    # Byte 0 of each block: high bits beyond the mode field must not matter.
    first = np.array([0b000, 0b100, 0b001, 0b00010, 0b00011, 0b11100011, 0b11110, 0b10011, 0b11111], np.uint8)
    blocks = np.zeros((3, 3, 16), dtype=np.uint8)
    blocks[..., 0] = first.reshape(3, 3)
    assert mode_histogram(blocks) == {1: 2, 2: 1, 3: 1, 10: 1, 11: 2, "reserved": 2}
    # Reserved codes decode to zero, as the decoder does for them.
    assert not bc6h.decode_blocks(blocks.reshape(-1, 16)[[7, 8]], signed=False).any()
