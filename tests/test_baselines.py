"""Baseline codecs (BC1/BC5 through quicktex, ASTC through astcenc, naive BC6 from training) on a real material:
files read back by independent decoders (texture2ddecoder, OpenImageIO), exact sizes, plausible quality, scores
that equal a direct per-mip comparison, and `bcf compress --baselines` end to end.

Input: tests/data/chainmail_128 (ambientCG Chainmail004 at 128 px, separate roughness / metalness, DirectX normal).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
import texture2ddecoder
from bcf.core import options
from bcf.core.report import baselines
from bcf.core import pipeline as compress
from bcf.core.material import images
from bcf.core.material.roles import TEXTURES
from bcf.core.material.texture_set import TextureSet, load_material
from bcf.core.options import CompressOptions
from bcf.core.report.report_json import read_report
from bcf.core.fit.sampling import ReferenceMaterial
from bcf_command import run_bcf

CHAINMAIL = Path(__file__).resolve().parent / "data" / "chainmail_128"
CODEC_BASELINES = options.baseline_names(("bc1_bc5", "astc"))
ASTC_MAGIC = bytes([0x13, 0xAB, 0xA1, 0x5C])

# PSNR over all mips measured on chainmail_128 (BC: quicktex level 18; ASTC: thorough), with a margin of a few dB:
# bc1_bc5 full 36.4 / half 35.3, ASTC 12x12 28.2 / 27.9, 8x8 33.7 / 32.9, 6x6 37.9 / 36.4.
PLAUSIBLE_DB = {"bc1_bc5_full": (33, 40), "bc1_bc5_half": (32, 39), "astc_12x12_full": (25, 32),
                "astc_12x12_half": (24, 31), "astc_8x8_full": (30, 37), "astc_8x8_half": (29, 36),
                "astc_6x6_full": (34, 42), "astc_6x6_half": (33, 40)}


@pytest.fixture(scope="module")
def chainmail() -> TextureSet:
    return load_material(CHAINMAIL)


@pytest.fixture(scope="module")
def reference(chainmail: TextureSet) -> ReferenceMaterial:
    return ReferenceMaterial(chainmail.channels, "wrap")


@pytest.fixture(scope="module")
def encoded(chainmail: TextureSet, reference: ReferenceMaterial, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Every BC/ASTC baseline: (report, decoder, decoded baseline, folder with its files)."""
    root = tmp_path_factory.mktemp("baselines")
    out = {}
    for name in CODEC_BASELINES:
        decoded = baselines.encode_baseline(options.BASELINES[name], chainmail.channels)
        baselines.write_baseline_files(decoded, root / name)
        scored, decoder = baselines.run_codec_baseline(name, chainmail.channels, reference)
        out[name] = (scored, decoder, decoded, root / name)
    return out


def _expected_bytes(name: str, width: int, height: int) -> int:
    """Blocks of the full chain to 1x1: BC 8 + 16 + 8 bytes per 4x4 block, ASTC 3 x 16 bytes per n x n block."""
    spec = options.BASELINES[name]
    if spec.half:
        width, height = width // 2, height // 2
    total = 0
    for level in range(max(width, height).bit_length()):
        w, h = max(1, width >> level), max(1, height >> level)
        n = spec.block
        total += math.ceil(w / n) * math.ceil(h / n) * (32 if spec.codec == "bc1_bc5" else 48)
    return total


# ------------------------------------------------------------------------------------------- sizes, files


@pytest.mark.parametrize("name", CODEC_BASELINES)
def test_size_is_every_block_of_every_mip(name: str, encoded: dict, chainmail: TextureSet) -> None:
    scored, _, decoded, folder = encoded[name]
    expected = _expected_bytes(name, chainmail.width, chainmail.height)
    assert decoded.size_bytes == scored.size_bytes == expected
    assert scored.bits_per_texel == pytest.approx(expected * 8 / (128 * 128))
    header = 148 if name.startswith("bc") else 16  # DDS with DX10 header per file; .astc per mip
    files = sorted(folder.iterdir())
    assert sum(p.stat().st_size - header for p in files) == expected


@pytest.mark.parametrize("name", ["bc1_bc5_full", "bc1_bc5_half"])
def test_bc_files_decode_the_same_in_independent_decoders(name: str, encoded: dict) -> None:
    """texture2ddecoder reproduces quicktex's decode exactly; OpenImageIO's DDS reader (its own BC1 palette
    rounding) within 2/255, on every mip of albedo.dds, normal.dds, arm.dds."""
    _, _, decoded, folder = encoded[name]
    for texture in decoded.textures:
        path = folder / f"{texture.name}.dds"
        assert oiio.ImageBuf(str(path)).nmiplevels == len(texture.levels) == len(decoded.mips)
        for level, blocks in enumerate(texture.levels):
            ours = decoded.mips[level][..., texture.channels]
            h, w, c = ours.shape
            decode = texture2ddecoder.decode_bc5 if texture.name == "normal" else texture2ddecoder.decode_bc1
            bgra = np.frombuffer(decode(blocks, w, h), np.uint8).reshape(h, w, 4)
            np.testing.assert_array_equal(bgra[..., [2, 1, 0]][..., :c], np.round(ours * 255).astype(np.uint8))
            from_file = oiio.ImageBuf(str(path), 0, level).get_pixels(oiio.FLOAT)[..., :c]
            assert np.abs(from_file - ours).max() <= 2.001 / 255, (texture.name, level)
            assert np.abs(from_file - ours).mean() < 0.6 / 255  # measured 0.35 / 255 on albedo


@pytest.mark.parametrize("name", ["astc_12x12_full", "astc_8x8_half", "astc_6x6_full"])
def test_astc_files_decode_the_same_in_an_independent_decoder(name: str, encoded: dict) -> None:
    """Each .astc file: Arm's header (magic, block size, 24-bit sizes), blocks that texture2ddecoder decodes to
    astcenc's decode within 1/255 (unorm8 vs fp16 rounding)."""
    _, _, decoded, folder = encoded[name]
    n = options.BASELINES[name].block
    for texture in decoded.textures:
        for level, ours in enumerate(decoded.mips):
            data = (folder / f"{texture.name}_mip{level}.astc").read_bytes()
            h, w = ours.shape[:2]
            assert data[:4] == ASTC_MAGIC and tuple(data[4:7]) == (n, n, 1)
            assert (int.from_bytes(data[7:10], "little"), int.from_bytes(data[10:13], "little")) == (w, h)
            bgra = np.frombuffer(texture2ddecoder.decode_astc(data[16:], w, h, n, n), np.uint8).reshape(h, w, 4)
            c = ours[..., texture.channels].shape[-1]
            assert np.abs(bgra[..., [2, 1, 0]][..., :c] / 255.0 - ours[..., texture.channels]).max() <= 1.001 / 255


# --------------------------------------------------------------------------------------------- scores


@pytest.mark.parametrize("name", CODEC_BASELINES)
def test_quality_is_plausible(name: str, encoded: dict) -> None:
    scored = encoded[name][0]
    low, high = PLAUSIBLE_DB[name]
    assert low < scored.aggregate.psnr.all < high, scored.aggregate.psnr
    assert 0.7 < scored.aggregate.ssim.all <= 1.0


def test_more_bits_score_higher(encoded: dict) -> None:
    psnr = {name: encoded[name][0].aggregate.psnr.all for name in CODEC_BASELINES}
    for resolution in ("full", "half"):
        assert psnr[f"astc_12x12_{resolution}"] < psnr[f"astc_8x8_{resolution}"] < psnr[f"astc_6x6_{resolution}"]
    for codec in ("bc1_bc5", "astc_12x12", "astc_8x8", "astc_6x6"):
        assert psnr[f"{codec}_half"] < psnr[f"{codec}_full"]


def _magnify_2x_wrap(image: np.ndarray) -> np.ndarray:
    """Bilinear 2x magnification with wrap addressing at texel centres, written out: output texel 2k reads source
    coordinate k - 0.25 (weights 1/4, 3/4 on k - 1, k), output 2k + 1 reads k + 0.25 (3/4, 1/4 on k, k + 1)."""
    def along(a: np.ndarray, axis: int) -> np.ndarray:
        even = 0.25 * np.roll(a, 1, axis) + 0.75 * a
        odd = 0.75 * a + 0.25 * np.roll(a, -1, axis)
        return np.stack([even, odd], axis=axis + 1).reshape(
            *a.shape[:axis], 2 * a.shape[axis], *a.shape[axis + 1:])
    return along(along(image, 0), 1)


@pytest.mark.parametrize("name", ["bc1_bc5_full", "astc_8x8_half"])
def test_scores_equal_a_direct_comparison_of_the_decoded_mips(name: str, encoded: dict,
                                                              reference: ReferenceMaterial) -> None:
    """Through the trilinear sampler at texel centres, a full-resolution baseline reads its own mip m at mip m, a
    half-resolution one its mip m - 1, and at mip 0 its top mip magnified 2x bilinearly: the per-mip MSE equals
    numpy's on those images."""
    scored, _, decoded, _ = encoded[name]
    half = options.BASELINES[name].half
    for entry in scored.per_mip:
        target = reference.mip(entry.mip).permute(1, 2, 0).numpy()
        if half:
            image = _magnify_2x_wrap(decoded.mips[0]) if entry.mip == 0 else decoded.mips[entry.mip - 1]
        else:
            image = decoded.mips[entry.mip]
        for texture, channels in TEXTURES.items():
            mse = float(np.mean((target[..., channels] - image[..., channels]) ** 2))
            assert getattr(entry.mse, texture) == pytest.approx(mse, rel=1e-4, abs=1e-9), (entry.mip, texture)


def test_parse_baselines() -> None:
    assert options.parse_baselines("all") == list(options.BASELINES)
    assert options.parse_baselines("naive, bc") == ["bc1_bc5_full", "bc1_bc5_half", "naive_bc6"]
    assert options.parse_baselines("astc_6x6_half,bc1_bc5_full") == ["bc1_bc5_full", "astc_6x6_half"]
    with pytest.raises(ValueError, match="unknown baseline 'etc2'"):
        options.parse_baselines("bc,etc2")


def test_encode_baseline_refuses_naive_bc6(chainmail: TextureSet) -> None:
    with pytest.raises(ValueError, match="naive_bc6 comes from training"):
        baselines.encode_baseline(options.BASELINES["naive_bc6"], chainmail.channels)


# ------------------------------------------------------------------------------------------ end to end


def test_compress_with_baselines(chainmail: TextureSet, tmp_path: Path) -> None:
    """compress_material with BC and naive baselines: report.json entries with our keys, files under baselines/,
    the naive BC6 variant the same size as ours and, in the paper's fit (random start, one mode), far below it:
    phase 2 is what makes its BC6H features work."""
    out = tmp_path / "out"
    notes: list[str] = []
    options = CompressOptions(preset="paper", block_mode=11, phase1_iterations=150, phase2_iterations=150,
                              batch_size=4096)
    rep = compress.compress_material(chainmail, options, out, baselines=["bc1_bc5_half", "naive_bc6"],
                                     note=notes.append)
    assert list(rep.baselines) == ["bc1_bc5_half", "naive_bc6"]
    assert read_report(out) == rep
    stored = json.loads((out / "report.json").read_text())["baselines"]["bc1_bc5_half"]
    assert set(stored) >= {"aggregate", "per_mip", "size_bytes", "bits_per_texel", "encode_s", "description"}
    assert [m.mip for m in rep.baselines["bc1_bc5_half"].per_mip] == [m.mip for m in rep.per_mip]
    naive = rep.baselines["naive_bc6"]
    assert naive.size_bytes == rep.size.total_bytes
    assert naive.aggregate.psnr.all < rep.aggregate.psnr.all - 1.0, (naive.aggregate.psnr, rep.aggregate.psnr)
    assert sorted(p.name for p in (out / compress.BASELINES_FOLDER / "bc1_bc5_half").iterdir()) == \
        ["albedo.dds", "arm.dds", "normal.dds"]
    assert not (out / compress.BASELINES_FOLDER / "naive_bc6").exists()  # its blocks are ours before phase 2
    assert (out / "report.html").stat().st_size > 10_000
    assert any("baseline bc1_bc5_half" in n for n in notes)


def test_cli_baselines(tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = run_bcf("compress", CHAINMAIL, "-o", out, "--preset", "fast", "--phase1-iterations", "30",
                     "--phase2-iterations", "30", "--batch-size", "1024", "--baselines", "astc_12x12_full,naive")
    assert result.returncode == 0, result.stderr
    for name in ("astc_12x12_full", "naive_bc6", "ours"):
        assert name in result.stdout  # the comparison table
    assert set(read_report(out).baselines) == {"astc_12x12_full", "naive_bc6"}
    bad = run_bcf("compress", CHAINMAIL, "-o", tmp_path / "bad", "--preset", "fast", "--baselines", "bc,etc2")
    assert bad.returncode == 2 and "unknown baseline 'etc2'" in bad.stderr and "Traceback" not in bad.stderr
    assert not (tmp_path / "bad").exists()


def test_baseline_chain_uses_the_reference_filter(chainmail: TextureSet) -> None:
    """The codecs compress the same box-filtered chain the reference pyramid is built from."""
    chain = images.mip_chain(chainmail.channels)
    reference = ReferenceMaterial(chainmail.channels, "wrap")
    for level in range(reference.levels):
        np.testing.assert_array_equal(chain[level], reference.mip(level).permute(1, 2, 0).numpy())
