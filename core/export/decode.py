"""The one reference decoder: an export folder read back from its files alone (`load_export`: manifest, BC6H
textures decoded bit-exactly, fp16 weights evaluated in float32) and evaluated at any (u, v, s): per texel of a
material mip (`render_mip`, `decode_export` to images) or over a region (`render_region`).

Reports, baselines, the shader tests and the preview all decode through here, so they score what an engine
would see.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Literal, Optional, Sequence

import numpy as np
import torch

from bcf.core.codec import bc6h, containers
from bcf.core.export.artifacts import (DecoderEntry, ExportError, FeatureTextureEntry, Manifest,
                                       read_decoder_bytes, read_feature_texture, read_manifest)
from bcf.core.fit.model import Decoder, FeatureTextureSpec, NeuralMaterial, StaticFeatures
from bcf.core.fit.sampling import texel_centres
from bcf.core.material import images
from bcf.core.material.roles import material_images

__all__ = ["DecoderFunction", "ExportedMaterial", "decode_export", "decoded_file_names", "load_export",
           "render_mip", "render_region"]

RENDER_CHUNK = 1 << 18  # samples per decoder call: bounds memory on 2K mips

DecoderFunction = Callable[[torch.Tensor, float], torch.Tensor]  # (uv (N, 2), s) -> (N, C)


class ExportedMaterial:
    """An export folder read back: its manifest and the model that decodes it (fp16 weights evaluated in
    float32, BC6H textures decoded bit-exactly), built from the files alone."""

    def __init__(self, manifest: Manifest, model: NeuralMaterial, directory: Path):
        self.manifest = manifest
        self.model = model
        self.directory = directory


def _feature_levels(directory: Path, entry: FeatureTextureEntry) -> list[torch.Tensor]:
    texture = read_feature_texture(directory, entry)
    levels = []
    for number, blocks in enumerate(texture.levels):
        w, h = containers.mip_size(texture.width, texture.height, number)
        image = bc6h.decode_image(blocks, w, h, signed=False).astype(np.float32)
        levels.append(torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))))
    return levels


def _read_decoder(directory: Path, entry: DecoderEntry) -> Decoder:
    values = np.frombuffer(read_decoder_bytes(directory, entry), dtype="<f2")  # every layer inside: checked
    layers = []
    for layer in entry.layers:
        w = values[layer.weight_offset:layer.weight_offset + layer.inputs * layer.outputs]
        b = values[layer.bias_offset:layer.bias_offset + layer.outputs]
        layers.append((torch.from_numpy(w.astype(np.float32).reshape(layer.outputs, layer.inputs)),
                       torch.from_numpy(b.astype(np.float32))))
    return Decoder.from_layers(layers)  # two layers, relu then identity, 12-N-8: checked by the manifest model


def load_export(directory: Path) -> ExportedMaterial:
    """Read an export folder into a model; raises ExportError naming the first bad file."""
    directory = Path(directory)
    manifest = read_manifest(directory)
    specs = tuple(FeatureTextureSpec(t.width, t.height, t.mips, t.lod_bias) for t in manifest.feature_textures)
    levels = [_feature_levels(directory, t) for t in manifest.feature_textures]
    decoder = _read_decoder(directory, manifest.decoder)
    model = NeuralMaterial(StaticFeatures(specs, levels), decoder, manifest.address)
    return ExportedMaterial(manifest, model.eval(), directory)


@torch.no_grad()
def render_mip(decoder: DecoderFunction, width: int, height: int, s: float,
               jitter: Optional[torch.Generator] = None, device: str | torch.device = "cpu") -> torch.Tensor:
    """Evaluate a decoder at the texel centres (or, with `jitter`, one random point per texel) of a
    width x height grid at scale s: -> (C, height, width)."""
    rows = max(1, RENDER_CHUNK // width)
    out: Optional[torch.Tensor] = None
    for y in range(0, height, rows):  # filled in place: one full-size image at a time, never a list and its copy
        part = decoder(texel_centres(width, height, slice(y, y + rows), device, jitter), s)
        if out is None:
            out = torch.empty(part.shape[1], height, width, dtype=part.dtype, device=part.device)
        out[:, y:y + rows] = part.T.reshape(-1, min(rows, height - y), width)
    assert out is not None
    return out


@torch.no_grad()
def render_region(decoder: DecoderFunction, width: int, height: int, s: float, x: int, y: int,
                  size: int) -> torch.Tensor:
    """Evaluate a decoder at the texel centres of the size x size square at (x, y) of a width x height grid at
    scale s: -> (C, size, size). For crops of a large mip without rendering all of it."""
    xs = (torch.arange(x, x + size, dtype=torch.float32) + 0.5) / width
    ys = (torch.arange(y, y + size, dtype=torch.float32) + 0.5) / height
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    uv = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=1)
    return decoder(uv, s).T.reshape(-1, size, size)


def decoded_file_names(mip: int, extension: str) -> dict[str, str]:
    """Names `decode_export` writes for one mip: albedo.png, ... for mip 0; albedo_mip<N>.png, ... else."""
    suffix = "" if mip == 0 else f"_mip{mip}"
    return {name: f"{name}{suffix}{extension}" for name in ("albedo", "normal", "arm")}


def decode_export(folder: Path, output: Path, mips: Sequence[int], extension: Literal[".png", ".exr"] = ".png",
                  png_bits: Literal[8, 16] = 8,
                  on_file: Optional[Callable[[Path], None]] = None) -> list[Path]:
    """The reference decoder: reconstruct albedo / normal / ARM images of the given mips of an export
    folder from its files alone, evaluating at each texel centre of the material mip (scale s = mip).
    Returns the written paths."""
    exported = load_export(folder)
    manifest = exported.manifest
    for mip in mips:
        if not 0 <= mip < manifest.mips:
            raise ExportError(f"mip {mip} does not exist; the material has mips 0..{manifest.mips - 1}", file=folder)
    output.mkdir(parents=True, exist_ok=True)
    written = []
    for mip in mips:
        w, h = max(1, manifest.width >> mip), max(1, manifest.height >> mip)
        channels = render_mip(exported.model, w, h, float(mip)).permute(1, 2, 0).numpy()
        for name, image in material_images(channels).items():
            path = output / decoded_file_names(mip, extension)[name]
            images.write_rgb(path, image, png_bits)
            written.append(path)
            if on_file is not None:
                on_file(path)
    return written
