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

from pydantic import BaseModel, ConfigDict, ValidationError

from bcf.core.codec import containers
from bcf.core.errors import InputError
from bcf.core.fit.model import FEATURE_CHANNELS, BlockFeatures, Decoder, NeuralMaterial
from bcf.core.material.texture_set import MaterialSource
from bcf.core.options import Address, ResolvedOptions
from bcf.core.version import GENERATOR

__all__ = ["DECODER_FILE", "MANIFEST_FILE", "ExportError", "Manifest", "feature_file", "read_manifest",
           "sha256_hex", "write_export"]

FORMAT_NAME = "bcf-neural-material"
FORMAT_VERSION = 1
MANIFEST_FILE = "manifest.json"
DECODER_FILE = "decoder.bin"


def feature_file(index: int) -> str:
    return f"features_{index}.dds"


class ExportError(InputError):
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
    address: Address
    feature_textures: list[FeatureTextureEntry]
    decoder: DecoderEntry
    outputs: list[OutputEntry]
    options: ResolvedOptions


def sha256_hex(data: bytes) -> str:
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
            bytes=sum(level.nbytes for level in levels), sha256=sha256_hex(path.read_bytes())))
    data, layers = _decoder_bytes(model.decoder)
    (directory / DECODER_FILE).write_bytes(data)
    manifest = Manifest(
        generator=GENERATOR, material=source, width=source.width, height=source.height, mips=mips,
        address=model.address, feature_textures=textures,
        decoder=DecoderEntry(layers=layers, bytes=len(data), sha256=sha256_hex(data)),
        outputs=_outputs(source), options=options)
    (directory / MANIFEST_FILE).write_text(manifest.model_dump_json(indent=2) + "\n")
    return manifest


def read_manifest(directory: Path) -> Manifest:
    """manifest.json of an export folder; ExportError for a folder that is not one."""
    path = Path(directory) / MANIFEST_FILE
    if not Path(directory).is_dir():
        raise ExportError("not a directory", file=directory)
    if not path.is_file():
        raise ExportError(f"missing; is {directory} a 'bcf compress' output folder?", file=path)
    try:
        return Manifest.model_validate(json.loads(path.read_text()))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ExportError(f"not valid JSON: {exc}", file=path) from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ExportError(f"not a bcf manifest ({where}: {first['msg']})", file=path) from None
