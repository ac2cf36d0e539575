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
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from bcf.core.codec import containers
from bcf.core.errors import InputError
from bcf.core.files import file_sha256
from bcf.core.fit.model import (FEATURE_CHANNELS, FEATURE_TEXTURES, OUTPUT_CHANNELS, BlockFeatures, Decoder,
                                NeuralMaterial)
from bcf.core.material.texture_set import MaterialSource
from bcf.core.options import Address, ResolvedOptions
from bcf.core.version import GENERATOR

__all__ = ["DECODER_FILE", "MANIFEST_FILE", "ExportError", "Manifest", "feature_file", "read_decoder_bytes",
           "read_feature_texture", "read_manifest", "sha256_hex", "verify_files", "write_export"]

FORMAT_NAME = "bcf-neural-material"
FORMAT_VERSION = 1
MANIFEST_FILE = "manifest.json"
DECODER_FILE = "decoder.bin"


def feature_file(index: int) -> str:
    return f"features_{index}.dds"


class ExportError(InputError):
    """An export folder that is incomplete, inconsistent or corrupt; the message names the file."""


# A manifest is read from a folder anyone may have edited: every size is bounded (D3D's largest texture side,
# BC6H's mip count for it, the widest decoder bcf writes), so reading one never allocates more than such an
# export needs, and every file is a plain name inside the folder.
MAX_TEXTURE_SIDE = 16384
MAX_MIPS = 15
MAX_LAYER_WIDTH = 64
MAX_MANIFEST_BYTES = 1 << 20  # bcf writes a few KiB


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _plain_file_name(name: str) -> str:
    if not name or name in (".", "..") or Path(name).name != name or "\\" in name:
        raise ValueError(f"{name!r} is not a file name inside the export folder")
    return name


FileName = Annotated[str, AfterValidator(_plain_file_name)]
Side = Annotated[int, Field(ge=1, le=MAX_TEXTURE_SIDE)]
Sha256 = Annotated[str, Field(pattern="^[0-9a-f]{64}$")]


class FeatureTextureEntry(_Strict):
    file: FileName
    format: Literal["BC6H_UF16"] = "BC6H_UF16"
    dxgi_format: Literal[95] = 95
    width: Side
    height: Side
    mips: int = Field(ge=1, le=MAX_MIPS)
    lod_bias: float = Field(ge=-MAX_MIPS, le=MAX_MIPS)  # b_i of eq. 11: log2(max(width / material width, ...))
    mlp_inputs: list[int]  # which MLP inputs the texture's R, G, B feed
    bytes: int = Field(ge=0)  # BC6H payload of all mips (GPU memory), without the DDS header
    sha256: Sha256


class LayerEntry(_Strict):
    inputs: int = Field(ge=1, le=MAX_LAYER_WIDTH)
    outputs: int = Field(ge=1, le=MAX_LAYER_WIDTH)
    activation: Literal["relu", "identity"]
    weight_offset: int = Field(ge=0)  # in fp16 elements from the start of decoder.bin; outputs x inputs, row-major
    bias_offset: int = Field(ge=0)  # in fp16 elements; `outputs` values


class DecoderEntry(_Strict):
    file: FileName = DECODER_FILE
    dtype: Literal["float16"] = "float16"
    byte_order: Literal["little"] = "little"
    layers: list[LayerEntry] = Field(min_length=2, max_length=2)
    bytes: int = Field(ge=0)
    sha256: Sha256

    @model_validator(mode="after")
    def _the_reference_mlp(self) -> "DecoderEntry":
        """Two layers, relu then identity, from the 12 features to the 8 material channels (docs/FORMAT.md)."""
        first, second = self.layers
        if (first.activation, second.activation) != ("relu", "identity"):
            raise ValueError("expected two layers, relu then identity")
        if (first.inputs, first.outputs, second.outputs) != (FEATURE_TEXTURES * FEATURE_CHANNELS, second.inputs,
                                                             OUTPUT_CHANNELS):
            raise ValueError(f"expected layers {FEATURE_TEXTURES * FEATURE_CHANNELS}-N-{OUTPUT_CHANNELS}, found "
                             f"{first.inputs}-{first.outputs}-{second.inputs}-{second.outputs}")
        return self


class OutputEntry(_Strict):
    name: Literal["albedo", "normal", "arm"]
    channels: list[Annotated[int, Field(ge=0, lt=OUTPUT_CHANNELS)]] = Field(min_length=1, max_length=3)  # in order
    meaning: str


class Manifest(_Strict):
    format: Literal["bcf-neural-material"] = FORMAT_NAME
    format_version: Literal[1] = FORMAT_VERSION
    generator: str
    material: MaterialSource
    width: Side  # of the source material
    height: Side
    mips: int = Field(ge=1, le=MAX_MIPS)  # material mip levels the model was trained on: scales s in [0, mips - 1]
    address: Address
    feature_textures: list[FeatureTextureEntry] = Field(min_length=FEATURE_TEXTURES, max_length=FEATURE_TEXTURES)
    decoder: DecoderEntry
    outputs: list[OutputEntry] = Field(min_length=3, max_length=3)
    options: ResolvedOptions

    @model_validator(mode="after")
    def _consistent(self) -> "Manifest":
        """Texture i feeds MLP inputs 3i..3i+2 (the reference decoder concatenates in texture order), and no
        texture or material has more mips than its size allows."""
        for i, texture in enumerate(self.feature_textures):
            if texture.mlp_inputs != list(range(FEATURE_CHANNELS * i, FEATURE_CHANNELS * (i + 1))):
                raise ValueError(f"feature_textures.{i}.mlp_inputs: expected {FEATURE_CHANNELS * i}.."
                                 f"{FEATURE_CHANNELS * (i + 1) - 1}, found {texture.mlp_inputs}")
            if texture.mips > max(texture.width, texture.height).bit_length():
                raise ValueError(f"feature_textures.{i}: {texture.mips} mips for {texture.width}x{texture.height}")
        if self.mips > max(self.width, self.height).bit_length():
            raise ValueError(f"{self.mips} mips for a {self.width}x{self.height} material")
        return self


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


def _read_checked(path: Path, sha256: str) -> bytes:
    if not path.is_file():
        raise ExportError("missing", file=path)
    data = path.read_bytes()
    if sha256_hex(data) != sha256:
        raise ExportError("contents do not match the manifest's sha256 (modified or corrupt)", file=path)
    return data


def read_feature_texture(directory: Path, entry: FeatureTextureEntry) -> containers.BC6HTexture:
    """A feature texture that matches its manifest entry: SHA-256, then the DDS header's size, mips, format and
    payload bytes; ExportError naming the file otherwise."""
    path = Path(directory) / entry.file
    _read_checked(path, entry.sha256)
    try:
        texture = containers.read_dds(path)
    except containers.ContainerError as exc:
        raise ExportError(str(exc)) from None
    payload = sum(level.nbytes for level in texture.levels)
    found = (texture.width, texture.height, len(texture.levels), texture.signed, payload)
    if found != (entry.width, entry.height, entry.mips, False, entry.bytes):
        raise ExportError(f"{texture.width}x{texture.height}, {len(texture.levels)} mips, "
                          f"{'SF16' if texture.signed else 'UF16'}, {payload:,} bytes of blocks; the manifest says "
                          f"{entry.width}x{entry.height}, {entry.mips} mips, UF16, {entry.bytes:,} bytes", file=path)
    return texture


def read_decoder_bytes(directory: Path, entry: DecoderEntry) -> bytes:
    """decoder.bin, if it matches its manifest entry (SHA-256 and size) and holds every layer the entry
    places in it; ExportError naming the file otherwise."""
    path = Path(directory) / entry.file
    data = _read_checked(path, entry.sha256)
    if len(data) != entry.bytes:
        raise ExportError(f"{len(data):,} bytes; the manifest says {entry.bytes:,}", file=path)
    values = len(data) // 2  # fp16
    for number, layer in enumerate(entry.layers):
        end = max(layer.weight_offset + layer.inputs * layer.outputs, layer.bias_offset + layer.outputs)
        if end > values:
            raise ExportError(f"{values} fp16 values; the manifest's layer {number} needs {end}", file=path)
    return data


def verify_files(directory: Path, manifest: Manifest) -> int:
    """Check every file the manifest lists against its SHA-256 and size (a feature texture's DDS header too);
    ExportError naming the first that does not match. Returns how many files were checked."""
    for texture in manifest.feature_textures:
        read_feature_texture(directory, texture)
    read_decoder_bytes(directory, manifest.decoder)
    return len(manifest.feature_textures) + 1


def read_manifest(directory: Path) -> Manifest:
    """manifest.json of an export folder; ExportError for a folder that is not one."""
    path = Path(directory) / MANIFEST_FILE
    if not Path(directory).is_dir():
        raise ExportError("not a directory", file=directory)
    if not path.is_file():
        raise ExportError(f"missing; is {directory} a 'bcf compress' output folder?", file=path)
    if path.stat().st_size > MAX_MANIFEST_BYTES:
        raise ExportError(f"{path.stat().st_size:,} bytes, more than any bcf manifest ({MAX_MANIFEST_BYTES:,} at "
                          "most)", file=path)
    try:
        return Manifest.model_validate(json.loads(path.read_text()))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ExportError(f"not valid JSON: {exc}", file=path) from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        raise ExportError(f"not a bcf manifest ({where}: {first['msg']})", file=path) from None
