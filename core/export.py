"""The exported neural material: four BC6H feature textures, fp16 decoder weights and a manifest
(docs/FORMAT.md specifies all three), written from a fit and read back into a model (the reference decoder).

    OUT/features_0.dds .. features_3.dds   mipmapped BC6H_UF16 (DXGI 95), the trained blocks as they are
    OUT/decoder.bin                         fp16 little-endian: W1, b1, W2, b2 (W row-major, outputs x inputs)
    OUT/manifest.json                       `Manifest`: sizes, formats, layers, outputs, LOD biases, options
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, ValidationError

from bcf import __version__
from bcf.core import bc6h, containers
from bcf.core.material import MaterialSource
from bcf.core.model import (FEATURE_CHANNELS, BlockFeatures, Decoder, FeatureTextureSpec, NeuralMaterial,
                            StaticFeatures)
from bcf.core.options import ResolvedOptions

__all__ = ["DECODER_FILE", "MANIFEST_FILE", "ExportError", "ExportedMaterial", "Manifest", "feature_file",
           "load_export", "write_export"]

FORMAT_NAME = "bcf-neural-material"
FORMAT_VERSION = 1
MANIFEST_FILE = "manifest.json"
DECODER_FILE = "decoder.bin"


def feature_file(index: int) -> str:
    return f"features_{index}.dds"


class ExportError(ValueError):
    """An export folder that is incomplete, inconsistent or corrupt; the message names the file."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FeatureTextureEntry(_Strict):
    file: str
    format: Literal["BC6H_UF16"] = "BC6H_UF16"
    dxgi_format: Literal[95] = 95
    width: int
    height: int
    mips: int
    lod_bias: float  # b_i of eq. 11: log2(max(width / material width, height / material height))
    mlp_inputs: list[int]  # which MLP inputs the texture's R, G, B feed
    bytes: int  # BC6H payload of all mips (GPU memory), without the DDS header
    sha256: str


class LayerEntry(_Strict):
    inputs: int
    outputs: int
    activation: Literal["relu", "identity"]
    weight_offset: int  # in fp16 elements from the start of decoder.bin; outputs x inputs, row-major
    bias_offset: int  # in fp16 elements; `outputs` values


class DecoderEntry(_Strict):
    file: str = DECODER_FILE
    dtype: Literal["float16"] = "float16"
    byte_order: Literal["little"] = "little"
    layers: list[LayerEntry]
    bytes: int
    sha256: str


class OutputEntry(_Strict):
    name: Literal["albedo", "normal", "arm"]
    channels: list[int]  # MLP outputs, in order
    meaning: str


class Manifest(_Strict):
    format: Literal["bcf-neural-material"] = FORMAT_NAME
    format_version: Literal[1] = FORMAT_VERSION
    generator: str
    material: MaterialSource
    width: int  # of the source material
    height: int
    mips: int  # material mip levels the model was trained on: scales s in [0, mips - 1]
    address: Literal["wrap", "clamp"]
    feature_textures: list[FeatureTextureEntry]
    decoder: DecoderEntry
    outputs: list[OutputEntry]
    options: ResolvedOptions


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _outputs(source: MaterialSource) -> list[OutputEntry]:
    return [
        OutputEntry(name="albedo", channels=[0, 1, 2], meaning="base colour R, G, B as stored in the source "
                    "(sRGB-encoded), in [0, 1]"),
        OutputEntry(name="normal", channels=[3, 4], meaning="tangent-space normal x, y as stored in the source, "
                    f"(n + 1) / 2 in [0, 1], {source.normal_convention} convention; "
                    "z = sqrt(max(0, 1 - x^2 - y^2)) with x, y mapped back to [-1, 1]"),
        OutputEntry(name="arm", channels=[5, 6, 7], meaning="ambient occlusion, roughness, metalness in [0, 1]"),
    ]


def _decoder_bytes(decoder: Decoder) -> tuple[bytes, list[LayerEntry]]:
    """fp16 little-endian layers, scale/offset folded in; each layer's weights then biases."""
    chunks, entries, offset = [], [], 0
    layers = decoder.folded_layers()
    for number, (weight, bias) in enumerate(layers):
        w = weight.detach().cpu().numpy().astype("<f2")
        b = bias.detach().cpu().numpy().astype("<f2")
        activation = "relu" if number < len(layers) - 1 else "identity"
        entries.append(LayerEntry(inputs=w.shape[1], outputs=w.shape[0], activation=activation,
                                  weight_offset=offset, bias_offset=offset + w.size))
        offset += w.size + b.size
        chunks += [w.tobytes(), b.tobytes()]
    return b"".join(chunks), entries


def write_export(directory: Path, model: NeuralMaterial, source: MaterialSource, mips: int,
                 options: ResolvedOptions) -> Manifest:
    """Write the feature textures, decoder.bin and manifest.json of a phase-2 model into `directory`
    (which must exist). The BC6H blocks are the model's rounded parameters, encoded as they are."""
    if not isinstance(model.features, BlockFeatures):
        raise TypeError("only block features (after phase 2 starts) can be exported")
    textures = []
    for i, spec in enumerate(model.features.specs):
        levels = tuple(model.features.blocks(i, level) for level in range(spec.levels))
        path = directory / feature_file(i)
        containers.write_dds(path, containers.BC6HTexture(spec.width, spec.height, False, levels))
        textures.append(FeatureTextureEntry(
            file=path.name, width=spec.width, height=spec.height, mips=spec.levels, lod_bias=spec.lod_bias,
            mlp_inputs=list(range(FEATURE_CHANNELS * i, FEATURE_CHANNELS * (i + 1))),
            bytes=sum(level.nbytes for level in levels), sha256=_sha256(path.read_bytes())))
    data, layers = _decoder_bytes(model.decoder)
    (directory / DECODER_FILE).write_bytes(data)
    manifest = Manifest(
        generator=f"bcf {__version__}", material=source, width=source.width, height=source.height, mips=mips,
        address=model.address, feature_textures=textures,
        decoder=DecoderEntry(layers=layers, bytes=len(data), sha256=_sha256(data)),
        outputs=_outputs(source), options=options)
    (directory / MANIFEST_FILE).write_text(manifest.model_dump_json(indent=2) + "\n")
    return manifest


# ------------------------------------------------------------------------------------------------- read


class ExportedMaterial:
    """An export folder read back: its manifest and the model that decodes it (fp16 weights evaluated in
    float32, BC6H textures decoded bit-exactly), built from the files alone."""

    def __init__(self, manifest: Manifest, model: NeuralMaterial, directory: Path):
        self.manifest = manifest
        self.model = model
        self.directory = directory


def read_manifest(directory: Path) -> Manifest:
    path = Path(directory) / MANIFEST_FILE
    if not Path(directory).is_dir():
        raise ExportError(f"{directory}: not a directory")
    if not path.is_file():
        raise ExportError(f"{path}: missing; is {directory} a 'bcf compress' output folder?")
    try:
        return Manifest.model_validate(json.loads(path.read_text()))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ExportError(f"{path}: not valid JSON: {exc}") from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ExportError(f"{path}: not a bcf manifest ({where}: {first['msg']})") from None


def _read_checked(path: Path, sha256: str) -> bytes:
    if not path.is_file():
        raise ExportError(f"{path}: missing")
    data = path.read_bytes()
    if _sha256(data) != sha256:
        raise ExportError(f"{path}: contents do not match the manifest's sha256 (modified or corrupt)")
    return data


def _read_feature_texture(directory: Path, entry: FeatureTextureEntry) -> list[torch.Tensor]:
    path = directory / entry.file
    _read_checked(path, entry.sha256)
    try:
        texture = containers.read_dds(path)
    except containers.ContainerError as exc:
        raise ExportError(str(exc)) from None
    found = (texture.width, texture.height, len(texture.levels), texture.signed)
    if found != (entry.width, entry.height, entry.mips, False):
        raise ExportError(f"{path}: {texture.width}x{texture.height}, {len(texture.levels)} mips, "
                          f"{'SF16' if texture.signed else 'UF16'}; the manifest says {entry.width}x"
                          f"{entry.height}, {entry.mips} mips, UF16")
    levels = []
    for number, blocks in enumerate(texture.levels):
        w, h = containers.mip_size(texture.width, texture.height, number)
        image = bc6h.decode_image(blocks, w, h, signed=False).astype(np.float32)
        levels.append(torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))))
    return levels


def _read_decoder(directory: Path, entry: DecoderEntry) -> Decoder:
    data = _read_checked(directory / entry.file, entry.sha256)
    values = np.frombuffer(data, dtype="<f2")
    layers = []
    for layer in entry.layers:
        end = layer.bias_offset + layer.outputs
        if end > values.size:
            raise ExportError(f"{directory / entry.file}: {values.size} fp16 values, the manifest's layers need {end}")
        w = values[layer.weight_offset:layer.weight_offset + layer.inputs * layer.outputs]
        b = values[layer.bias_offset:end]
        layers.append((torch.from_numpy(w.astype(np.float32).reshape(layer.outputs, layer.inputs)),
                       torch.from_numpy(b.astype(np.float32))))
    if len(layers) != 2 or [l.activation for l in entry.layers] != ["relu", "identity"]:
        raise ExportError(f"{directory / MANIFEST_FILE}: expected two layers (relu, identity)")
    return Decoder.from_layers(layers)


def load_export(directory: Path) -> ExportedMaterial:
    """Read an export folder into a model; raises ExportError naming the first bad file."""
    directory = Path(directory)
    manifest = read_manifest(directory)
    specs = tuple(FeatureTextureSpec(t.width, t.height, t.mips, t.lod_bias) for t in manifest.feature_textures)
    levels = [_read_feature_texture(directory, t) for t in manifest.feature_textures]
    decoder = _read_decoder(directory, manifest.decoder)
    model = NeuralMaterial(StaticFeatures(specs, levels), decoder, manifest.address)
    return ExportedMaterial(manifest, model.eval(), directory)
