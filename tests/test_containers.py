"""Tests of bcf.core.containers: round trips, the DDS and KTX2 layouts checked field by field against the specs,
two independent decoders (OpenImageIO, Mesa) reading our files and data, and malformed files."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from bcf.core.codec.containers import (
    BC6HTexture,
    ContainerError,
    full_mip_count,
    mip_size,
    read_dds,
    read_ktx2,
    read_texture,
    write_dds,
    write_ktx2,
)
from reference_decoders import MesaBC6HDecoder, decode_with_oiio, oiio_mip_sizes

KTX2_IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
WRITERS = {"dds": (write_dds, read_dds), "ktx2": (write_ktx2, read_ktx2)}


def block_grid(width: int, height: int, level: int) -> tuple[int, int]:
    w, h = mip_size(width, height, level)
    return (h + 3) // 4, (w + 3) // 4


def random_texture(seed: int, width: int, height: int, signed: bool, levels: int | None = None,
                   mode11: bool = False) -> BC6HTexture:
    """Random block bytes; with `mode11` every block is a valid mode-11 block (low five bits 0b00011)."""
    rng = np.random.default_rng(seed)
    count = full_mip_count(width, height) if levels is None else levels
    chain = []
    for level in range(count):
        blocks = rng.integers(0, 256, (*block_grid(width, height, level), 16), dtype=np.uint8)
        if mode11:
            blocks[..., 0] = (blocks[..., 0] & 0xE0) | 0x03
        chain.append(blocks)
    return BC6HTexture(width, height, signed, tuple(chain))


def assert_same_texture(got: BC6HTexture, want: BC6HTexture) -> None:
    assert (got.width, got.height, got.signed) == (want.width, want.height, want.signed)
    assert len(got.levels) == len(want.levels)
    for level, (a, b) in enumerate(zip(got.levels, want.levels)):
        assert a.dtype == np.uint8 and a.shape == b.shape, f"level {level}"
        assert np.array_equal(a, b), f"level {level} blocks differ"


# ------------------------------------------------------------------------------------------------ sizes


@pytest.mark.parametrize(("width", "height", "count"), [(1024, 512, 11), (20, 12, 5), (1, 1, 1), (1, 9, 4),
                                                        (4096, 4096, 13), (1023, 1, 10)])
def test_full_mip_count(width: int, height: int, count: int) -> None:
    assert full_mip_count(width, height) == count


def test_mip_sizes_of_non_square_chain() -> None:
    sizes = [mip_size(1024, 512, level) for level in range(11)]
    assert sizes == [(1024, 512), (512, 256), (256, 128), (128, 64), (64, 32), (32, 16), (16, 8), (8, 4),
                     (4, 2), (2, 1), (1, 1)]
    assert [mip_size(20, 12, level) for level in range(5)] == [(20, 12), (10, 6), (5, 3), (2, 1), (1, 1)]


def test_texture_validates_its_levels() -> None:
    good = random_texture(0, 20, 12, False)
    with pytest.raises(ValueError, match="level 1 must be a uint8 array of shape"):
        BC6HTexture(20, 12, False, (good.levels[0], good.levels[0]))
    with pytest.raises(ValueError, match="uint8"):
        BC6HTexture(20, 12, False, (good.levels[0].astype(np.int16),))
    with pytest.raises(ValueError, match="1 to 5 levels"):
        BC6HTexture(20, 12, False, good.levels + (good.levels[-1],))
    with pytest.raises(ValueError, match="1 to 5 levels"):
        BC6HTexture(20, 12, False, ())
    with pytest.raises(ValueError, match="width must be a positive int"):
        BC6HTexture(0, 12, False, good.levels[:1])


# ------------------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("kind", sorted(WRITERS))
@pytest.mark.parametrize("signed", [False, True], ids=["uf16", "sf16"])
@pytest.mark.parametrize(("width", "height", "levels"), [(1024, 512, None), (20, 12, None), (20, 12, 1),
                                                         (1, 1, None), (3, 1025, 4)])
def test_round_trip(tmp_path: Path, kind: str, signed: bool, width: int, height: int, levels: int | None) -> None:
    write, read = WRITERS[kind]
    texture = random_texture(width * 7 + height, width, height, signed, levels)
    path = tmp_path / f"t.{kind}"
    write(path, texture)
    assert_same_texture(read(path), texture)
    assert_same_texture(read_texture(path), texture)


def test_read_texture_dispatches_on_magic_not_extension(tmp_path: Path) -> None:
    texture = random_texture(3, 20, 12, True)
    write_dds(tmp_path / "really_dds.ktx2", texture)
    write_ktx2(tmp_path / "really_ktx2.dds", texture)
    assert_same_texture(read_texture(tmp_path / "really_dds.ktx2"), texture)
    assert_same_texture(read_texture(tmp_path / "really_ktx2.dds"), texture)


# ------------------------------------------------------------------------------------- layout vs specs


@pytest.mark.parametrize(("width", "height", "signed", "levels"), [(1024, 512, False, None), (20, 12, True, None),
                                                                   (20, 12, False, 1)])
def test_dds_layout(tmp_path: Path, width: int, height: int, signed: bool, levels: int | None) -> None:
    texture = random_texture(5, width, height, signed, levels)
    path = tmp_path / "t.dds"
    write_dds(path, texture)
    data = path.read_bytes()
    count = len(texture.levels)
    assert data[:4] == b"DDS "
    size, flags, h, w, linear, depth, mips = struct.unpack_from("<7I", data, 4)
    assert (size, h, w, depth, mips) == (124, height, width, 0, count)
    # DDSD_CAPS | HEIGHT | WIDTH | PIXELFORMAT | MIPMAPCOUNT | LINEARSIZE
    assert flags == 0x1 | 0x2 | 0x4 | 0x1000 | 0x20000 | 0x80000
    assert linear == texture.levels[0].nbytes
    assert data[32:76] == bytes(44)
    assert struct.unpack_from("<II4s5I", data, 76) == (32, 0x4, b"DX10", 0, 0, 0, 0, 0)
    caps = struct.unpack_from("<5I", data, 108)
    # DDSCAPS_TEXTURE, plus COMPLEX | MIPMAP for a mip chain
    assert caps == ((0x1000 | 0x8 | 0x400000) if count > 1 else 0x1000, 0, 0, 0, 0)
    assert struct.unpack_from("<5I", data, 128) == (96 if signed else 95, 3, 0, 1, 0)
    offset = 148
    for blocks in texture.levels:  # largest first, no padding
        assert data[offset:offset + blocks.nbytes] == blocks.tobytes()
        offset += blocks.nbytes
    assert offset == len(data)


def parse_kvd(data: bytes, offset: int, length: int) -> list[tuple[str, bytes]]:
    """Key/value pairs per ktxspec.adoc, asserting each length field is 4-aligned and padding is zero."""
    pairs, cursor, end = [], offset, offset + length
    while cursor < end:
        assert cursor % 4 == 0
        (n,) = struct.unpack_from("<I", data, cursor)
        assert n >= 2
        key, _, value = data[cursor + 4:cursor + 4 + n].partition(b"\0")
        pairs.append((key.decode("utf-8"), value))
        padded = (n + 3) // 4 * 4
        assert data[cursor + 4 + n:cursor + 4 + padded] == bytes(padded - n)
        cursor += 4 + padded
    assert cursor == end  # sum(ceil(len_i / 4) * 4) + 4 n == kvdByteLength
    return pairs


@pytest.mark.parametrize(("width", "height", "signed", "levels"), [(1024, 512, False, None), (20, 12, True, None),
                                                                   (20, 12, False, 1), (1, 1, True, None)])
def test_ktx2_layout(tmp_path: Path, width: int, height: int, signed: bool, levels: int | None) -> None:
    texture = random_texture(6, width, height, signed, levels)
    path = tmp_path / "t.ktx2"
    write_ktx2(path, texture)
    data = path.read_bytes()
    n = len(texture.levels)
    assert data[:12] == KTX2_IDENTIFIER
    header = struct.unpack_from("<9I", data, 12)
    # vkFormat, typeSize 1, pixelWidth, pixelHeight, pixelDepth 0, layerCount 0, faceCount 1, levelCount, scheme 0
    assert header == (144 if signed else 143, 1, width, height, 0, 0, 1, n, 0)
    dfd_off, dfd_len, kvd_off, kvd_len, sgd_off, sgd_len = struct.unpack_from("<4I2Q", data, 48)
    assert dfd_off == 80 + 24 * n and (sgd_off, sgd_len) == (0, 0)

    # Data Format Descriptor (Khronos Data Format spec, KHR_DF_MODEL_BC6H section)
    words = struct.unpack_from("<11I", data, dfd_off)
    assert words[0] == dfd_len == kvd_off - dfd_off == 44  # dfdTotalSize
    assert words[1] == 0  # vendorId KHRONOS, descriptorType BASICFORMAT
    assert (words[2] & 0xFFFF, words[2] >> 16) == (2, 40)  # versionNumber 2 (1.3), descriptorBlockSize 24 + 16
    assert struct.unpack_from("<4B", data, dfd_off + 12) == (133, 1, 1, 0)  # BC6H, BT709, LINEAR, ALPHA_STRAIGHT
    assert struct.unpack_from("<4B", data, dfd_off + 16) == (3, 3, 0, 0)  # texelBlockDimension: 4x4 blocks
    assert struct.unpack_from("<8B", data, dfd_off + 20) == (16, 0, 0, 0, 0, 0, 0, 0)  # bytesPlane0..7
    bit_offset, bit_length, channel = struct.unpack_from("<HBB", data, dfd_off + 28)
    assert (bit_offset, bit_length) == (0, 127)
    assert channel == (0xC0 if signed else 0x80)  # COLOR (0) with FLOAT (and SIGNED for SF16) qualifiers
    assert words[8] == 0  # samplePosition0..3
    assert struct.unpack_from("<2f", data, dfd_off + 36) == ((-1.0 if signed else 0.0), 1.0)

    # Key/value data: right after the DFD, sorted by key, with a KTXwriter string
    assert kvd_off % 4 == 0
    pairs = parse_kvd(data, kvd_off, kvd_len)
    keys = [key for key, _ in pairs]
    assert keys == sorted(keys) and len(set(keys)) == len(keys)
    writer = dict(pairs)["KTXwriter"]
    assert writer.endswith(b"\0") and writer[:-1].decode("utf-8").startswith("bcf")

    # Level index and mip level array: smallest level at the lowest offset, each aligned to lcm(16, 4) = 16
    index = [struct.unpack_from("<3Q", data, 80 + 24 * p) for p in range(n)]
    for p, (offset, length, uncompressed) in enumerate(index):
        rows, cols = block_grid(width, height, p)
        assert length == uncompressed == rows * cols * 16
        assert offset % 16 == 0
        assert data[offset:offset + length] == texture.levels[p].tobytes()
    first = index[-1][0]
    data_start = kvd_off + kvd_len
    assert first == (data_start + 15) // 16 * 16 and data[data_start:first] == bytes(first - data_start)
    for p in range(1, n):
        assert index[p][0] + index[p][1] == index[p - 1][0]  # level p sits just before the larger level p - 1
    assert index[0][0] + index[0][1] == len(data)
    # ktxspec "levels[p].byteLength": size from the first level to the end of the file
    assert len(data) - first == index[0][1] + sum((index[p][1] + 15) // 16 * 16 for p in range(1, n))


# --------------------------------------------------------------------------------- independent decoders


@pytest.mark.gl
@pytest.mark.parametrize(("width", "height", "signed"), [(1024, 512, False), (20, 12, True)])
def test_oiio_and_mesa_agree_on_every_level(tmp_path: Path, mesa: MesaBC6HDecoder, width: int, height: int,
                                            signed: bool) -> None:
    texture = random_texture(11, width, height, signed, mode11=True)
    dds, ktx2 = tmp_path / "t.dds", tmp_path / "t.ktx2"
    write_dds(dds, texture)
    write_ktx2(ktx2, texture)
    expected_sizes = [mip_size(width, height, level) for level in range(len(texture.levels))]
    assert oiio_mip_sizes(dds) == expected_sizes
    from_mesa = mesa.decode(read_ktx2(ktx2))  # Mesa decodes the blocks our KTX2 reader returns
    assert len(from_mesa) == len(expected_sizes)
    for level, (w, h) in enumerate(expected_sizes):
        from_oiio = decode_with_oiio(dds, level)  # OIIO decodes our DDS file
        assert from_oiio.shape == from_mesa[level].shape == (h, w, 3)
        assert np.array_equal(from_oiio.view(np.uint16), from_mesa[level].view(np.uint16)), f"level {level}"
    # Guard against two decoders agreeing on nothing: random mode-11 blocks are not all zero or all equal.
    assert np.unique(from_mesa[0].view(np.uint16)).size > 100


# ------------------------------------------------------------------------------------- malformed inputs

Mutation = Callable[[bytearray], bytes]


def put(offset: int, fmt: str, *values: int | bytes) -> Mutation:
    def mutate(data: bytearray) -> bytes:
        struct.pack_into(fmt, data, offset, *values)
        return bytes(data)
    return mutate


def cut(length: int) -> Mutation:
    return lambda data: bytes(data[:length])


def swap_ktx2_level_offsets(a: int, b: int) -> Mutation:
    def mutate(data: bytearray) -> bytes:
        off_a, off_b = (struct.unpack_from("<Q", data, 80 + 24 * p)[0] for p in (a, b))
        struct.pack_into("<Q", data, 80 + 24 * a, off_b)
        struct.pack_into("<Q", data, 80 + 24 * b, off_a)
        return bytes(data)
    return mutate


# 64x32, 7 levels: the last three levels are one block each; the DDS file is 148 + 2768 bytes.
DDS_CASES: dict[str, tuple[Mutation, str]] = {
    "empty": (cut(0), "truncated"),
    "cut_in_magic": (cut(2), "truncated"),
    "cut_in_header": (cut(50), "truncated"),
    "cut_in_pixelformat": (cut(90), "truncated"),
    "cut_in_dx10_header": (cut(140), "truncated"),
    "cut_in_level_0": (cut(1000), "truncated"),
    "cut_last_byte": (cut(-1), "truncated"),
    "wrong_magic": (put(0, "4s", b"DDX "), "not a DDS file"),
    "bc7_dxgi_format": (put(128, "<I", 98), "unsupported dxgiFormat 98"),
    "legacy_dxt1_fourcc": (put(84, "4s", b"DXT1"), "legacy FourCC"),
    "not_fourcc": (put(80, "<I", 0x40), "not FourCC"),
    "zero_width": (put(16, "<I", 0), "zero image size"),
    "zero_height": (put(12, "<I", 0), "zero image size"),
    "too_many_mips": (put(28, "<I", 8), "too many mip levels"),
    "huge_size": (put(12, "<2I", 0xFFFFFFFF, 0xFFFFFFFF), "truncated"),
    "trailing_bytes": (lambda data: bytes(data) + bytes(16), "unexpected bytes"),
    "texture_array": (put(140, "<I", 2), "arrays"),
    "texture3d": (put(132, "<I", 4), "TEXTURE2D"),
    "cube_map": (put(112, "<I", 0x200 | 0xFC00), "cube"),
    "bad_header_size": (put(4, "<I", 100), "DDS_HEADER size"),
}

# 64x32, 7 levels, UF16.
KTX2_CASES: dict[str, tuple[Mutation, str]] = {
    "empty": (cut(0), "truncated"),
    "cut_in_identifier": (cut(7), "truncated"),
    "cut_in_header": (cut(30), "truncated"),
    "cut_in_index": (cut(70), "truncated"),
    "cut_in_level_index": (cut(150), "truncated"),
    "cut_in_dfd": (cut(80 + 24 * 7 + 20), "truncated"),
    "cut_in_level_data": (cut(400), "truncated"),
    "cut_last_byte": (cut(-1), "truncated"),
    "ktx1_identifier": (put(5, "2s", b"11"), "not a KTX2 file"),
    "bc7_vk_format": (put(12, "<I", 145), "unsupported vkFormat 145"),
    "zero_width": (put(20, "<I", 0), "zero image size"),
    "zero_height": (put(24, "<I", 0), "zero image size"),
    "too_many_levels": (put(40, "<I", 8), "too many mip levels"),
    "level_count_zero": (put(40, "<I", 0), "levelCount 0"),
    "supercompressed_zstd": (put(44, "<I", 2), "supercompressionScheme 2"),
    "supercompressed_basislz": (put(44, "<I", 1), "supercompressionScheme 1"),
    "level_length_mismatch": (put(80 + 24 * 1 + 8, "<Q", 496), "level 1 byteLength 496"),
    "uncompressed_length_mismatch": (put(80 + 24 * 2 + 16, "<Q", 0), "uncompressedByteLength 0"),
    "misaligned_level": (lambda data: put(80 + 8 * 0, "<Q", struct.unpack_from("<Q", data, 80)[0] + 4)(data),
                         "not 16-byte aligned"),
    "levels_out_of_order": (swap_ktx2_level_offsets(5, 6), "smallest first"),
    "level_over_header": (put(80 + 24 * 6, "<Q", 16), "overlaps the metadata"),
    "array_texture": (put(32, "<I", 2), "only plain 2D"),
    "cube_map": (put(36, "<I", 6), "only plain 2D"),
    "type_size": (put(16, "<I", 2), "typeSize 2"),
    "dfd_model_bc7": (put(80 + 24 * 7 + 12, "<B", 134), "colorModel 134"),
    "dfd_total_size": (put(80 + 24 * 7, "<I", 48), "dfdTotalSize 48"),
    "dfd_signed_but_uf16": (put(80 + 24 * 7 + 31, "<B", 0xC0), "SIGNED"),
    "kvd_bad_length": (put(80 + 24 * 7 + 44, "<I", 1000), "key/value"),
    "sgd_present": (put(72, "<Q", 8), "sgdByteLength 8"),
}


# Per container: its cases, writer, reader, and the cases whose file read_texture cannot attribute to a format.
CONTAINERS = {".dds": (DDS_CASES, write_dds, read_dds, ("wrong_magic", "empty", "cut_in_magic")),
              ".ktx2": (KTX2_CASES, write_ktx2, read_ktx2, ("ktx1_identifier", "empty", "cut_in_identifier"))}


@pytest.mark.parametrize("suffix, case", [(suffix, case) for suffix, (cases, *_) in CONTAINERS.items()
                                          for case in sorted(cases)])
def test_malformed_container(tmp_path: Path, suffix: str, case: str) -> None:
    cases, write, read, unattributable = CONTAINERS[suffix]
    mutate, problem = cases[case]
    good = tmp_path / f"good{suffix}"
    write(good, random_texture(1 if suffix == ".dds" else 2, 64, 32, False))
    bad = tmp_path / f"{case}{suffix}"
    bad.write_bytes(mutate(bytearray(good.read_bytes())))
    for reader in (read, read_texture):
        if reader is read_texture and case in unattributable:
            continue  # read_texture cannot tell which format such a file was meant to be
        with pytest.raises(ContainerError, match=problem) as info:
            reader(bad)
        assert str(bad) in str(info.value)


def test_read_texture_rejects_unknown_and_missing_files(tmp_path: Path) -> None:
    png = tmp_path / "image.dds"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    with pytest.raises(ContainerError, match="neither a DDS nor a KTX2 file"):
        read_texture(png)
    with pytest.raises(ContainerError, match="cannot read file"):
        read_texture(tmp_path / "missing.ktx2")
    assert issubclass(ContainerError, ValueError)
