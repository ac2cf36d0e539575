"""Conventional texture codecs as baselines, scored exactly like our own export.

Each baseline compresses the material's box-filtered mip chain (`images.mip_chain` of the 8 stored channels,
the same filter as the reference pyramid) texture by texture, down to 1x1, as an engine would ship it:

- ``bc1_bc5_full`` / ``bc1_bc5_half``: BC1 albedo, BC5 normal (x, y), BC1 ARM (the paper's "BC"), at the
  material's resolution or half of it (the paper's "BC 2048 / 1024"). Encoder: quicktex (rgbcx) at its highest
  level, 18, with 3-colour blocks allowed; etcpak measured 3.7 dB lower on these materials (docs/peers.md).
- ``astc_<n>x<n>_full`` / ``_half`` for n = 12, 8, 6: ASTC LDR (linear) with Arm's astcenc at its "thorough"
  preset (quality 98), albedo and ARM as RGB, the normal's x, y as the R, G of an RG01 image: measured
  higher PSNR on x, y than astcenc's rrrg normal-map mode, which optimises angles.
- ``naive_bc6``: our own phase-1 features (the principal-component start when phase 1 has no iterations) put
  in blocks by the transition, without the emulated-BC6H phase 2 (the paper's Fig. 4): what the second phase
  buys. It comes from `training.fit`
  (`FitResult.naive_model`), so it exists only inside `compress.compress_material`.

A half-resolution baseline is evaluated like the full one: at mip m the renderer reads the baseline's
mip m - 1 (bilinear magnification of its top mip at m = 0), through the same trilinear sampler as the
neural features, at the texel centres of every reference mip.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from bcf.core.codec import containers
from bcf.core.export.decode import DecoderFunction
from bcf.core.fit.sampling import ReferenceMaterial, sample_trilinear
from bcf.core.material import images
from bcf.core.material.roles import TEXTURES
from bcf.core.options import BASELINES, Address, BaselineSpec
from bcf.core.report import metrics
from bcf.core.report import report_json as report

__all__ = ["ASTC_QUALITY", "BC1_LEVEL", "DecodedBaseline", "PyramidDecoder", "encode_baseline", "evaluate_baseline",
           "run_codec_baseline", "write_baseline_files"]

BC1_LEVEL = 18  # quicktex's highest quality level
ASTC_QUALITY = 98.0  # astcenc's "thorough" preset

@dataclass
class EncodedTexture:
    """One texture of a baseline: which material channels it holds and its blocks, level by level."""

    name: str  # albedo | normal | arm
    channels: slice
    levels: list[bytes]


@dataclass
class DecodedBaseline:
    """A conventional codec's result: what the renderer would read (decoded mips, (h, w, 8) float32 in
    [0, 1], top mip first, down to 1x1) and what it stores."""

    spec: BaselineSpec
    description: str
    encoder: str
    width: int
    height: int
    mips: list[np.ndarray]
    textures: list[EncodedTexture]
    encode_s: float

    @property
    def size_bytes(self) -> int:
        return sum(len(level) for t in self.textures for level in t.levels)


# ------------------------------------------------------------------------------------------------ encoders


def _to_rgba8(image: np.ndarray) -> np.ndarray:
    """(h, w, 1..3) floats in [0, 1] -> (h, w, 4) uint8 RGBA, missing channels 0, alpha 255."""
    h, w, c = image.shape
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[..., :c] = np.round(np.clip(image, 0.0, 1.0) * 255.0)
    rgba[..., 3] = 255
    return rgba


def _bc_encode_level(image: np.ndarray, bc5: bool) -> tuple[bytes, np.ndarray]:
    """Encode one mip with quicktex: (blocks, decoded (h, w, 3 or 2) float32)."""
    import quicktex
    from quicktex.s3tc.bc1 import BC1Decoder, BC1Encoder
    from quicktex.s3tc.bc5 import BC5Decoder, BC5Encoder

    h, w = image.shape[:2]
    raw = quicktex.RawTexture.frombytes(_to_rgba8(image).tobytes(), w, h)
    if bc5:
        encoded, decoder, channels = BC5Encoder(0, 1).encode(raw), BC5Decoder(0, 1), 2
    else:
        encoded = BC1Encoder(BC1_LEVEL, BC1Encoder.ColorMode.ThreeColor).encode(raw)
        decoder, channels = BC1Decoder(), 3
    decoded = np.frombuffer(decoder.decode(encoded).tobytes(), np.uint8).reshape(h, w, 4)[..., :channels]
    return encoded.tobytes(), decoded.astype(np.float32) / 255.0


def _astc_context(block: int):  # -> astc_encoder.ASTCContext (imported lazily)
    """One astcenc context (LDR, thorough) per baseline: creating one is expensive, so mips share it."""
    from astc_encoder import ASTCConfig, ASTCContext, ASTCProfile

    return ASTCContext(ASTCConfig(ASTCProfile.LDR, block, block, 1, ASTC_QUALITY, 0), torch.get_num_threads())


def _astc_encode_level(image: np.ndarray, context) -> tuple[bytes, np.ndarray]:
    """Encode one mip with an `_astc_context`: (blocks, decoded (h, w, channels) float32)."""
    from astc_encoder import ASTCImage, ASTCSwizzle, ASTCType

    h, w, channels = image.shape
    # RGB1 for colours, RG01 for the normal's x, y; the decoded missing channels are ignored.
    swizzle = ASTCSwizzle.from_str("rgb1" if channels == 3 else "rg01")
    data = context.compress(ASTCImage(ASTCType.U8, w, h, 1, _to_rgba8(image).tobytes()), swizzle)
    out = ASTCImage(ASTCType.U8, w, h, 1)  # a fresh image: astc-encoder-py warns against reusing one
    context.decompress(data, out, swizzle)
    decoded = np.frombuffer(out.data, np.uint8).reshape(h, w, 4)[..., :channels]
    return bytes(data), decoded.astype(np.float32) / 255.0


def _package_version(name: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "unknown version"


def encode_baseline(spec: BaselineSpec, channels: np.ndarray) -> DecodedBaseline:
    """Compress the material `channels` ((H, W, 8) float32 in [0, 1]) with a BC or ASTC baseline: the full mip
    chain of each texture, encoded level by level, and decoded back."""
    if spec.codec == "naive_bc6":
        raise ValueError("naive_bc6 comes from training (compress.compress_material), not from encode_baseline")
    started = time.perf_counter()
    chain = images.mip_chain(channels)
    if spec.half:
        chain = chain[1:]
    decoded = [np.zeros_like(level) for level in chain]
    context = _astc_context(spec.block) if spec.codec == "astc" else None
    textures = []
    for name, channel_slice in TEXTURES.items():
        levels = []
        for level, out in zip(chain, decoded):
            image = level[..., channel_slice]
            if spec.codec == "bc1_bc5":
                blocks, values = _bc_encode_level(image, bc5=name == "normal")
            else:
                blocks, values = _astc_encode_level(image, context)
            levels.append(blocks)
            out[..., channel_slice] = values
        textures.append(EncodedTexture(name, channel_slice, levels))
    height, width = chain[0].shape[:2]
    if spec.codec == "bc1_bc5":
        description = f"BC1 albedo + BC5 normal xy + BC1 ARM at {width}x{height}, mips to 1x1"
        encoder = f"quicktex {_package_version('quicktex')} (rgbcx), level {BC1_LEVEL}, 3-colour blocks allowed"
    else:
        description = (f"ASTC {spec.block}x{spec.block} LDR: albedo RGB, normal xy (RG), ARM RGB at {width}x{height}, "
                       "mips to 1x1")
        encoder = f"astc-encoder-py {_package_version('astc-encoder-py')} (Arm astcenc), quality {ASTC_QUALITY:g}"
    return DecodedBaseline(spec, description, encoder, width, height, decoded, textures,
                           time.perf_counter() - started)


# ------------------------------------------------------------------------------------------- files, scoring


def write_baseline_files(baseline: DecodedBaseline, folder: Path) -> list[Path]:
    """The baseline's textures as files a texture tool can open: `<texture>.dds` (BC1_UNORM / BC5_UNORM, all
    mips) for BC, `<texture>_mip<N>.astc` (Arm's format, one file per mip) for ASTC."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for texture in baseline.textures:
        if baseline.spec.codec == "bc1_bc5":
            path = folder / f"{texture.name}.dds"
            dxgi = containers.DXGI_FORMAT_BC5_UNORM if texture.name == "normal" else containers.DXGI_FORMAT_BC1_UNORM
            containers.write_dds_blocks(path, baseline.width, baseline.height, dxgi, texture.levels)
            written.append(path)
        else:
            for level, data in enumerate(texture.levels):
                w, h = containers.mip_size(baseline.width, baseline.height, level)
                path = folder / f"{texture.name}_mip{level}.astc"
                containers.write_astc(path, w, h, (baseline.spec.block, baseline.spec.block), data)
                written.append(path)
    return written


class PyramidDecoder:
    """A `DecoderFunction` over decoded mips: trilinear lookups (eq. 10) at level s - lod_offset, what a
    texture unit does for a texture whose top mip is 2^lod_offset times smaller than the material."""

    def __init__(self, mips: Sequence[np.ndarray], address: Address, lod_offset: int = 0):
        self.levels = [torch.from_numpy(np.ascontiguousarray(m.transpose(2, 0, 1))) for m in mips]
        self.address = address
        self.lod_offset = lod_offset

    def __call__(self, uv: torch.Tensor, s: float) -> torch.Tensor:
        return sample_trilinear(self.levels.__getitem__, len(self.levels), uv, s - self.lod_offset, self.address)


def evaluate_baseline(description: str, encoder: str, width: int, height: int,
                      decoder: DecoderFunction, size_bytes: int, encode_s: float,
                      reference: ReferenceMaterial) -> report.BaselineReport:
    """Score any baseline decoder at every reference mip, exactly as the exported material is scored."""
    started = time.perf_counter()
    scores = metrics.evaluate(decoder, reference)
    evaluation = report.summarise(scores, [(m.shape[2], m.shape[1]) for m in reference.mips])
    return report.BaselineReport(
        description=description, encoder=encoder, width=width, height=height, aggregate=evaluation.aggregate,
        per_mip=evaluation.per_mip, size_bytes=size_bytes,
        bits_per_texel=size_bytes * 8 / (reference.width * reference.height), encode_s=encode_s,
        evaluation_s=time.perf_counter() - started)


def run_codec_baseline(name: str, channels: np.ndarray, reference: ReferenceMaterial,
                       folder: Path | None = None) -> tuple[report.BaselineReport, PyramidDecoder]:
    """Encode, optionally write the files to `folder`, decode and score one BC/ASTC baseline. Returns the
    scores and the decoder (for image crops)."""
    spec = BASELINES[name]
    baseline = encode_baseline(spec, channels)
    if folder is not None:
        write_baseline_files(baseline, folder)
    decoder = PyramidDecoder(baseline.mips, reference.address, lod_offset=1 if spec.half else 0)
    scored = evaluate_baseline(baseline.description, baseline.encoder, baseline.width, baseline.height,
                               decoder, baseline.size_bytes, baseline.encode_s, reference)
    return scored, decoder
