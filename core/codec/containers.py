"""DDS and KTX2 containers for mipmapped BC6H textures (and, for the baseline codecs, DDS files of other
block formats via `write_dds_blocks` and Arm `.astc` files via `write_astc`).

A texture is a chain of mip levels; level ``i`` is ``max(1, w >> i)`` by ``max(1, h >> i)`` texels, stored
as ``ceil(h_i / 4) x ceil(w_i / 4)`` BC6H blocks of 16 bytes, row-major (partial blocks at the right and bottom
edges are padded to whole blocks). Every multi-byte field in both formats is little-endian.

DDS (Microsoft "DDS_HEADER" / "DDS_HEADER_DXT10" reference pages)::

    0    magic "DDS "
    4    DDS_HEADER (124 bytes): size=124, flags, height, width, pitchOrLinearSize (= bytes of level 0),
         depth, mipMapCount, reserved1[11], DDS_PIXELFORMAT (32 bytes: size=32, flags=DDPF_FOURCC,
         fourCC="DX10", 5 unused dwords), caps, caps2, caps3, caps4, reserved2
    128  DDS_HEADER_DXT10 (20 bytes): dxgiFormat (95 BC6H_UF16 / 96 BC6H_SF16), resourceDimension=3
         (TEXTURE2D), miscFlag=0, arraySize=1, miscFlags2=0
    148  level 0, level 1, ... (largest first, no padding)

KTX2 (KhronosGroup/KTX-Specification, ktxspec.adoc)::

    0    identifier  AB 4B 54 58 20 32 30 BB 0D 0A 1A 0A
    12   vkFormat (143 BC6H_UFLOAT / 144 BC6H_SFLOAT), typeSize=1, pixelWidth, pixelHeight, pixelDepth=0,
         layerCount=0, faceCount=1, levelCount, supercompressionScheme=0            (9 x UInt32)
    48   dfdByteOffset, dfdByteLength, kvdByteOffset, kvdByteLength (UInt32), sgdByteOffset, sgdByteLength (UInt64)
    80   level index: levelCount x {byteOffset, byteLength, uncompressedByteLength} (UInt64), level 0 first
    ..   Data Format Descriptor: dfdTotalSize then one 40-byte basic descriptor block (Khronos Data Format
         spec, KHR_DF_MODEL_BC6H = 133, one 128-bit sample)
    ..   key/value data: {UInt32 length, key NUL value, pad to 4} sorted by key; here only KTXwriter
    ..   mip level array, smallest level first; each level starts on a multiple of lcm(16, 4) = 16 bytes
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from itertools import accumulate
from os import PathLike
from pathlib import Path
from typing import Sequence, Union

import numpy as np

from bcf.core.errors import InputError

__all__ = [
    "BC6HTexture",
    "ContainerError",
    "full_mip_count",
    "mip_size",
    "read_dds",
    "read_ktx2",
    "read_texture",
    "write_astc",
    "write_dds",
    "write_dds_blocks",
    "write_ktx2",
]

StrPath = Union[str, PathLike]

BLOCK_BYTES = 16
BLOCK_DIM = 4

# --- DDS constants (Microsoft dds-header, dds-pixelformat, dds-header-dxt10 reference pages) ---
DDS_MAGIC = b"DDS "
DDS_HEADER_SIZE = 124
DDS_PIXELFORMAT_SIZE = 32
DDS_DX10_SIZE = 20
DDS_DATA_OFFSET = 4 + DDS_HEADER_SIZE + DDS_DX10_SIZE  # 148
DDSD_CAPS = 0x1
DDSD_HEIGHT = 0x2
DDSD_WIDTH = 0x4
DDSD_PIXELFORMAT = 0x1000
DDSD_MIPMAPCOUNT = 0x20000
DDSD_LINEARSIZE = 0x80000
DDSD_DEPTH = 0x800000
DDPF_FOURCC = 0x4
DDSCAPS_COMPLEX = 0x8
DDSCAPS_TEXTURE = 0x1000
DDSCAPS_MIPMAP = 0x400000
DDSCAPS2_CUBEMAP = 0x200
DDSCAPS2_VOLUME = 0x200000
FOURCC_DX10 = b"DX10"
DXGI_FORMAT_BC1_UNORM = 71
DXGI_FORMAT_BC5_UNORM = 83
DXGI_FORMAT_BC6H_UF16 = 95
DXGI_FORMAT_BC6H_SF16 = 96
D3D10_RESOURCE_DIMENSION_TEXTURE2D = 3
D3D11_RESOURCE_MISC_TEXTURECUBE = 0x4

# --- KTX2 constants (ktxspec.adoc; Khronos Data Format spec, chapters/df.adoc and khr_df.h) ---
KTX2_IDENTIFIER = bytes([0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A])
KTX2_HEADER_SIZE = 80  # identifier + 9 UInt32 header fields + index
KTX2_LEVEL_ENTRY_SIZE = 24
VK_FORMAT_BC6H_UFLOAT_BLOCK = 143
VK_FORMAT_BC6H_SFLOAT_BLOCK = 144
KTX2_LEVEL_ALIGNMENT = math.lcm(BLOCK_BYTES, 4)  # "align(lcm(texel_block_size, 4)) mipPadding"
KHR_DF_MODEL_BC6H = 133
KHR_DF_PRIMARIES_BT709 = 1
KHR_DF_TRANSFER_LINEAR = 1
KHR_DF_VERSIONNUMBER_1_3 = 2
KHR_DF_SAMPLE_DATATYPE_SIGNED = 0x40
KHR_DF_SAMPLE_DATATYPE_FLOAT = 0x80
DFD_BLOCK_SIZE = 24 + 16  # basic descriptor block with one sample
DFD_TOTAL_SIZE = 4 + DFD_BLOCK_SIZE
FLOAT_BITS_0 = 0x00000000
FLOAT_BITS_1 = 0x3F800000
FLOAT_BITS_MINUS_1 = 0xBF800000
KTX_WRITER = "bcf"
ASTC_MAGIC = bytes([0x13, 0xAB, 0xA1, 0x5C])  # the .astc file identifier


class ContainerError(InputError):
    """A DDS or KTX2 file that is malformed or not a 2D BC6H texture this module supports."""


# ------------------------------------------------------------------------------------------------ sizes


def mip_size(width: int, height: int, level: int) -> tuple[int, int]:
    """(width, height) in texels of mip `level` of a `width` x `height` texture."""
    if width < 1 or height < 1 or level < 0:
        raise ValueError(f"mip_size needs positive sizes and level >= 0, got {width}x{height} level {level}")
    return max(1, width >> level), max(1, height >> level)


def full_mip_count(width: int, height: int) -> int:
    """Number of levels of a full chain down to 1x1: floor(log2(max(w, h))) + 1."""
    if width < 1 or height < 1:
        raise ValueError(f"full_mip_count needs positive sizes, got {width}x{height}")
    return max(width, height).bit_length()  # exact for ints, unlike math.log2


def _block_grid(width: int, height: int, level: int) -> tuple[int, int]:
    """(rows, columns) of 4x4 blocks in mip `level`."""
    w, h = mip_size(width, height, level)
    return -(-h // BLOCK_DIM), -(-w // BLOCK_DIM)


def _level_nbytes(width: int, height: int, level: int) -> int:
    rows, cols = _block_grid(width, height, level)
    return rows * cols * BLOCK_BYTES


# ---------------------------------------------------------------------------------------------- texture


@dataclass(frozen=True, eq=False)  # eq=False: generated __eq__/__hash__ would compare numpy arrays ambiguously
class BC6HTexture:
    """A 2D BC6H texture with a (possibly partial) mip chain; see the module docstring for the block layout."""

    width: int
    height: int
    signed: bool
    levels: tuple[np.ndarray, ...]

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"BC6HTexture.{name} must be a positive int, got {value!r}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "signed", bool(self.signed))
        object.__setattr__(self, "levels", tuple(self.levels))
        limit = full_mip_count(self.width, self.height)
        if not 1 <= len(self.levels) <= limit:
            raise ValueError(
                f"BC6HTexture of {self.width}x{self.height} needs 1 to {limit} levels, got {len(self.levels)}"
            )
        for i, blocks in enumerate(self.levels):
            expected = (*_block_grid(self.width, self.height, i), BLOCK_BYTES)
            if not isinstance(blocks, np.ndarray) or blocks.dtype != np.uint8 or blocks.shape != expected:
                got = (blocks.dtype, blocks.shape) if isinstance(blocks, np.ndarray) else type(blocks).__name__
                raise ValueError(f"BC6HTexture level {i} must be a uint8 array of shape {expected}, got {got}")

    def level_size(self, level: int) -> tuple[int, int]:
        """(width, height) in texels of `level`."""
        return mip_size(self.width, self.height, level)


# ------------------------------------------------------------------------------------------ file access


def _read_bytes(path: StrPath) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise ContainerError(f"cannot read file: {exc}", file=path) from exc


def _require(condition: bool, path: StrPath, problem: str) -> None:
    if not condition:
        raise ContainerError(problem, file=path)


def _unpack(fmt: str, data: bytes, offset: int, path: StrPath, what: str) -> tuple:
    """struct.unpack_from that reports truncation as a ContainerError naming the missing part."""
    size = struct.calcsize(fmt)
    _require(offset >= 0 and offset + size <= len(data), path,
             f"truncated: {what} needs bytes {offset}..{offset + size} but the file has {len(data)}")
    return struct.unpack_from(fmt, data, offset)


def _check_magic(path: StrPath, data: bytes, magic: bytes, kind: str) -> None:
    # A file cut inside the magic is reported as truncated, not as some other format.
    _require(len(data) >= len(magic) or not magic.startswith(data), path,
             f"truncated: {len(data)} bytes, shorter than the {kind} identifier")
    _require(data.startswith(magic), path, f"not a {kind} file (starts with {data[:len(magic)]!r})")


def _blocks_from(data: bytes, offset: int, width: int, height: int, level: int) -> np.ndarray:
    """Copy one level's blocks out of `data` (the caller has checked the bounds)."""
    rows, cols = _block_grid(width, height, level)
    flat = np.frombuffer(data, dtype=np.uint8, count=rows * cols * BLOCK_BYTES, offset=offset)
    return flat.reshape(rows, cols, BLOCK_BYTES).copy()  # copy: do not keep the whole file alive


def _check_texture_size(path: StrPath, width: int, height: int, levels: int) -> None:
    _require(width > 0 and height > 0, path, f"zero image size {width}x{height}")
    _require(levels >= 1, path, "no mip levels")
    limit = full_mip_count(width, height)
    _require(levels <= limit, path, f"too many mip levels: {levels} for {width}x{height} (at most {limit})")


# ---------------------------------------------------------------------------------------------------- DDS


def write_dds(path: StrPath, texture: BC6HTexture) -> None:
    """Write `texture` as a DDS file with the DX10 extension header, levels largest first."""
    dxgi = DXGI_FORMAT_BC6H_SF16 if texture.signed else DXGI_FORMAT_BC6H_UF16
    write_dds_blocks(path, texture.width, texture.height, dxgi,
                     [np.ascontiguousarray(level).tobytes() for level in texture.levels])


def write_dds_blocks(path: StrPath, width: int, height: int, dxgi_format: int, levels: Sequence[bytes]) -> None:
    """Write a DDS file (DX10 header) of any 4x4 block-compressed DXGI format from each level's blocks, largest
    level first. Also used for the BC1/BC5 baselines (DXGI_FORMAT_BC1_UNORM, DXGI_FORMAT_BC5_UNORM)."""
    count = len(levels)
    flags = DDSD_CAPS | DDSD_HEIGHT | DDSD_WIDTH | DDSD_PIXELFORMAT | DDSD_MIPMAPCOUNT | DDSD_LINEARSIZE
    caps = DDSCAPS_TEXTURE | (DDSCAPS_COMPLEX | DDSCAPS_MIPMAP if count > 1 else 0)
    pixel_format = struct.pack("<II4s5I", DDS_PIXELFORMAT_SIZE, DDPF_FOURCC, FOURCC_DX10, 0, 0, 0, 0, 0)
    header = struct.pack(
        "<7I44x32s5I",
        DDS_HEADER_SIZE, flags, height, width,
        len(levels[0]),  # linear size: bytes of the top level
        0, count, pixel_format, caps, 0, 0, 0, 0,
    )
    dx10 = struct.pack("<5I", dxgi_format, D3D10_RESOURCE_DIMENSION_TEXTURE2D, 0, 1, 0)
    Path(path).write_bytes(DDS_MAGIC + header + dx10 + b"".join(levels))


def write_astc(path: StrPath, width: int, height: int, block: tuple[int, int], data: bytes) -> None:
    """Write one ASTC image (one mip) as an Arm `.astc` file: a 16-byte header (magic 13 AB A1 5C, block
    x, y, z as bytes, then width, height, depth as 24-bit little-endian) followed by the blocks, row-major."""
    def u24(value: int) -> bytes:
        return value.to_bytes(3, "little")

    header = ASTC_MAGIC + bytes([block[0], block[1], 1]) + u24(width) + u24(height) + u24(1)
    Path(path).write_bytes(header + data)


def read_dds(path: StrPath) -> BC6HTexture:
    """Read a 2D BC6H DDS file (DX10 header) written by `write_dds` or any conforming writer."""
    return _parse_dds(path, _read_bytes(path))


def _parse_dds(path: StrPath, data: bytes) -> BC6HTexture:
    _check_magic(path, data, DDS_MAGIC, "DDS")
    size, flags, height, width, _linear, depth, mip_count = _unpack("<7I", data, 4, path, "DDS_HEADER")
    _require(size == DDS_HEADER_SIZE, path, f"DDS_HEADER size is {size}, expected {DDS_HEADER_SIZE}")
    pf_size, pf_flags, fourcc = _unpack("<II4s", data, 76, path, "DDS_PIXELFORMAT")
    (caps2,) = _unpack("<I", data, 112, path, "DDS_HEADER caps2")
    _require(pf_size == DDS_PIXELFORMAT_SIZE, path, f"DDS_PIXELFORMAT size is {pf_size}, expected 32")
    _require(pf_flags & DDPF_FOURCC != 0, path, "pixel format is not FourCC-coded, so it is not BC6H")
    _require(fourcc == FOURCC_DX10, path,
             f"legacy FourCC {fourcc!r} is not supported: BC6H needs the DX10 extended header")
    _require(not flags & DDSD_DEPTH and depth <= 1 and not caps2 & DDSCAPS2_VOLUME, path,
             "volume textures are not supported")
    _require(not caps2 & DDSCAPS2_CUBEMAP, path, "cube maps are not supported")
    dxgi, dimension, misc, array_size, _misc2 = _unpack("<5I", data, 128, path, "DDS_HEADER_DXT10")
    _require(dxgi in (DXGI_FORMAT_BC6H_UF16, DXGI_FORMAT_BC6H_SF16), path,
             f"unsupported dxgiFormat {dxgi}: only BC6H_UF16 (95) and BC6H_SF16 (96) are supported")
    _require(dimension == D3D10_RESOURCE_DIMENSION_TEXTURE2D, path,
             f"resourceDimension {dimension} is not TEXTURE2D (3)")
    _require(not misc & D3D11_RESOURCE_MISC_TEXTURECUBE, path, "cube maps are not supported")
    _require(array_size == 1, path, f"texture arrays are not supported (arraySize {array_size})")
    # Readers must not rely on DDSD_MIPMAPCOUNT (Microsoft's note): a count of 0 means just the top level.
    levels = max(mip_count, 1)
    _check_texture_size(path, width, height, levels)
    sizes = [_level_nbytes(width, height, i) for i in range(levels)]
    expected = DDS_DATA_OFFSET + sum(sizes)
    _require(len(data) >= expected, path,
             f"truncated: {levels} levels of {width}x{height} need {expected} bytes, the file has {len(data)}")
    _require(len(data) == expected, path,
             f"{len(data) - expected} unexpected bytes after the {levels} levels of {width}x{height}")
    offsets = accumulate(sizes[:-1], initial=DDS_DATA_OFFSET)
    blocks = tuple(_blocks_from(data, offset, width, height, i) for i, offset in enumerate(offsets))
    return BC6HTexture(width, height, dxgi == DXGI_FORMAT_BC6H_SF16, blocks)


# --------------------------------------------------------------------------------------------------- KTX2


def _align(value: int, alignment: int) -> int:
    return -(-value // alignment) * alignment


def _bc6h_dfd(signed: bool) -> bytes:
    """The Data Format Descriptor of VK_FORMAT_BC6H_{U,S}FLOAT_BLOCK (dfdTotalSize included).

    One basic descriptor block: 4x4 texel blocks of 16 bytes, one 128-bit sample with the FLOAT qualifier
    (plus SIGNED for SF16) and sample bounds -1.0f/0.0f .. 1.0f as float bit patterns. The Data Format spec's
    BC6H example tables print sampleUpper as 0x7F800000 (+inf) "-- 1.0f" and give the unsigned example a lower
    bound of -1.0f; we follow the stated values 1.0f (0x3F800000) and 0.0f for unsigned, as libktx does.
    """
    qualifiers = KHR_DF_SAMPLE_DATATYPE_FLOAT | (KHR_DF_SAMPLE_DATATYPE_SIGNED if signed else 0)
    return struct.pack(
        "<I6I4I",
        DFD_TOTAL_SIZE,
        0,  # vendorId KHRONOS (low 17 bits), descriptorType BASICFORMAT (high 15 bits)
        KHR_DF_VERSIONNUMBER_1_3 | (DFD_BLOCK_SIZE << 16),
        KHR_DF_MODEL_BC6H | (KHR_DF_PRIMARIES_BT709 << 8) | (KHR_DF_TRANSFER_LINEAR << 16),  # flags 0: straight
        (BLOCK_DIM - 1) | ((BLOCK_DIM - 1) << 8),  # texelBlockDimension0..3 = 4, 4, 1, 1 stored minus one
        BLOCK_BYTES,  # bytesPlane0 = 16, bytesPlane1..3 = 0
        0,  # bytesPlane4..7
        (0 << 0) | ((128 - 1) << 16) | (qualifiers << 24),  # bitOffset 0, bitLength 127, channel 0 (COLOR)
        0,  # samplePosition0..3
        FLOAT_BITS_MINUS_1 if signed else FLOAT_BITS_0,
        FLOAT_BITS_1,
    )


def _kvd(entries: dict[str, bytes]) -> bytes:
    """Key/value data: sorted by key (code points), each entry padded to 4 bytes."""
    out = bytearray()
    for key in sorted(entries):
        pair = key.encode("utf-8") + b"\0" + entries[key]
        out += struct.pack("<I", len(pair)) + pair + b"\0" * (_align(len(pair), 4) - len(pair))
    return bytes(out)


def write_ktx2(path: StrPath, texture: BC6HTexture) -> None:
    """Write `texture` as KTX2 without supercompression; mip data smallest first, each level 16-byte aligned."""
    count = len(texture.levels)
    dfd = _bc6h_dfd(texture.signed)
    kvd = _kvd({"KTXwriter": KTX_WRITER.encode("utf-8") + b"\0"})
    dfd_offset = KTX2_HEADER_SIZE + KTX2_LEVEL_ENTRY_SIZE * count
    kvd_offset = dfd_offset + len(dfd)
    data_start = kvd_offset + len(kvd)
    # Lay out the levels smallest first; every level's length is a multiple of 16, so only the first pads.
    offsets = [0] * count
    cursor = data_start
    for level in reversed(range(count)):
        cursor = _align(cursor, KTX2_LEVEL_ALIGNMENT)
        offsets[level] = cursor
        cursor += _level_nbytes(texture.width, texture.height, level)
    vk_format = VK_FORMAT_BC6H_SFLOAT_BLOCK if texture.signed else VK_FORMAT_BC6H_UFLOAT_BLOCK
    out = bytearray(cursor)
    out[0:12] = KTX2_IDENTIFIER
    struct.pack_into("<9I", out, 12, vk_format, 1, texture.width, texture.height, 0, 0, 1, count, 0)
    struct.pack_into("<4I2Q", out, 48, dfd_offset, len(dfd), kvd_offset, len(kvd), 0, 0)
    for level, blocks in enumerate(texture.levels):
        nbytes = blocks.nbytes
        struct.pack_into("<3Q", out, KTX2_HEADER_SIZE + KTX2_LEVEL_ENTRY_SIZE * level, offsets[level], nbytes, nbytes)
        out[offsets[level]:offsets[level] + nbytes] = np.ascontiguousarray(blocks).tobytes()
    out[dfd_offset:kvd_offset] = dfd
    out[kvd_offset:data_start] = kvd
    Path(path).write_bytes(bytes(out))


def _check_ktx2_dfd(path: StrPath, data: bytes, offset: int, length: int, signed: bool) -> None:
    """Check that the DFD is the BC6H descriptor the vkFormat implies (its only sample's SIGNED bit included)."""
    _require(length >= DFD_TOTAL_SIZE, path, f"dfdByteLength {length} is too small for a BC6H descriptor")
    total, _vendor, version_size, model_word, dims, planes = _unpack("<6I", data, offset, path, "DFD")
    _require(total == length, path, f"dfdTotalSize {total} differs from dfdByteLength {length}")
    _require(version_size >> 16 >= DFD_BLOCK_SIZE, path, f"DFD block size {version_size >> 16} is too small")
    _require(model_word & 0xFF == KHR_DF_MODEL_BC6H, path,
             f"DFD colorModel {model_word & 0xFF} is not KHR_DF_MODEL_BC6H ({KHR_DF_MODEL_BC6H})")
    _require(dims == 0x0303, path, f"DFD texelBlockDimension {dims:#010x} is not 4x4x1x1")
    _require(planes & 0xFF == BLOCK_BYTES, path, f"DFD bytesPlane0 {planes & 0xFF} is not 16")
    (sample,) = _unpack("<I", data, offset + 28, path, "DFD sample")
    _require(bool(sample >> 24 & KHR_DF_SAMPLE_DATATYPE_SIGNED) == signed, path,
             "DFD sample SIGNED qualifier contradicts vkFormat")


def _check_ktx2_kvd(path: StrPath, data: bytes, offset: int, length: int) -> None:
    """Walk the key/value pairs so a malformed length is reported, not silently skipped."""
    end = offset + length
    cursor = offset
    while cursor < end:
        (pair_len,) = _unpack("<I", data, cursor, path, "key/value length")
        _require(pair_len >= 2 and cursor + 4 + pair_len <= end, path,
                 f"key/value entry at byte {cursor} has impossible length {pair_len}")
        _require(b"\0" in data[cursor + 4:cursor + 4 + pair_len], path, f"key at byte {cursor} is not NUL-terminated")
        cursor += 4 + _align(pair_len, 4)
    _require(cursor == end, path, f"key/value data overruns kvdByteLength {length}")


def read_ktx2(path: StrPath) -> BC6HTexture:
    """Read a 2D BC6H KTX2 file (no supercompression, no arrays, no cube maps)."""
    return _parse_ktx2(path, _read_bytes(path))


def _parse_ktx2(path: StrPath, data: bytes) -> BC6HTexture:
    _check_magic(path, data, KTX2_IDENTIFIER, "KTX2")
    (vk_format, type_size, width, height, depth, layers, faces, count, scheme) = _unpack(
        "<9I", data, 12, path, "KTX2 header")
    _require(vk_format in (VK_FORMAT_BC6H_UFLOAT_BLOCK, VK_FORMAT_BC6H_SFLOAT_BLOCK), path,
             f"unsupported vkFormat {vk_format}: only BC6H_UFLOAT (143) and BC6H_SFLOAT (144) are supported")
    _require(scheme == 0, path, f"supercompressionScheme {scheme} is not supported (only 0, none)")
    _require(type_size == 1, path, f"typeSize {type_size} must be 1 for a block format")
    _require(depth == 0 and layers == 0 and faces == 1, path,
             f"only plain 2D textures are supported (pixelDepth {depth}, layerCount {layers}, faceCount {faces})")
    _require(count != 0, path, "levelCount 0 is not allowed for block-compressed formats")
    _check_texture_size(path, width, height, count)
    dfd_offset, dfd_length, kvd_offset, kvd_length, sgd_offset, sgd_length = _unpack(
        "<4I2Q", data, 48, path, "KTX2 index")
    _require(sgd_length == 0, path, f"sgdByteLength {sgd_length} must be 0 without supercompression")
    _require(dfd_offset + dfd_length <= len(data), path, "truncated: the DFD lies past the end of the file")
    _require(kvd_offset + kvd_length <= len(data), path, "truncated: key/value data lies past the end of the file")
    _check_ktx2_dfd(path, data, dfd_offset, dfd_length, vk_format == VK_FORMAT_BC6H_SFLOAT_BLOCK)
    _check_ktx2_kvd(path, data, kvd_offset, kvd_length)
    entries = [_unpack("<3Q", data, KTX2_HEADER_SIZE + KTX2_LEVEL_ENTRY_SIZE * i, path, f"level index entry {i}")
               for i in range(count)]
    # Level data must not overlap the header, index, DFD or key/value data (the smallest level comes first).
    metadata_end = max(KTX2_HEADER_SIZE + KTX2_LEVEL_ENTRY_SIZE * count, dfd_offset + dfd_length,
                       kvd_offset + kvd_length)
    _require(entries[-1][0] >= metadata_end, path,
             f"level {count - 1} offset {entries[-1][0]} overlaps the metadata ending at byte {metadata_end}")
    blocks = []
    for level, (offset, length, uncompressed) in enumerate(entries):
        expected = _level_nbytes(width, height, level)
        _require(length == expected and uncompressed == expected, path,
                 f"level {level} byteLength {length} / uncompressedByteLength {uncompressed} do not match the "
                 f"{expected} bytes of {'x'.join(map(str, mip_size(width, height, level)))} texels")
        _require(offset % KTX2_LEVEL_ALIGNMENT == 0, path, f"level {level} offset {offset} is not 16-byte aligned")
        _require(offset + length <= len(data), path,
                 f"truncated: level {level} needs bytes {offset}..{offset + length}, the file has {len(data)}")
        blocks.append(_blocks_from(data, offset, width, height, level))
    # The mip level array is ordered smallest level first: every level must end before the next larger begins.
    for level in range(1, count):
        _require(entries[level][0] + entries[level][1] <= entries[level - 1][0], path,
                 f"level {level} is not stored before level {level - 1} (levels must be smallest first)")
    return BC6HTexture(width, height, vk_format == VK_FORMAT_BC6H_SFLOAT_BLOCK, tuple(blocks))


# --------------------------------------------------------------------------------------------- dispatch


def read_texture(path: StrPath) -> BC6HTexture:
    """Read a DDS or KTX2 BC6H texture, choosing the format by the file's magic bytes."""
    data = _read_bytes(path)
    if data.startswith(DDS_MAGIC):
        return _parse_dds(path, data)
    if data.startswith(KTX2_IDENTIFIER):
        return _parse_ktx2(path, data)
    raise ContainerError(f"neither a DDS nor a KTX2 file (starts with {data[:12]!r})", file=path)
