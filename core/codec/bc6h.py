"""BC6H block codec: bit-exact decode and encode of all 14 modes, and the numeric half of the format
(paper eq. 9's inverse).

Everything is vectorised over blocks; the only Python loops run over the 14 modes, 32 partitions or
16 pixels of the format, never over blocks. The codec knows nothing about files or training.

Conventions
- A block is 16 bytes (uint8), read little-endian as a 128-bit integer, bit 0 first.
- Texels inside a block are in row-major pixel order 0..15; decoded texels have shape (..., 16, 3).
- "Half bits" are the 16-bit patterns of IEEE half floats. For UF16 the decoder yields 0..0x7BFF; for SF16
  a sign-magnitude pattern (0x8000 | magnitude for negatives).
- Mode numbers are Microsoft's 1..14. The mode field's value ("code") is what the block stores.

Sources: Microsoft's BC6H format page (unquantize, finish, sign extension, transform) and the OpenGL
ARB_texture_compression_bptc text (Table.F: the bit layout of every mode, whose notation we parse below;
Table.P2 and Table.A2: partitions and anchors).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cache

import numpy as np

BLOCK_BYTES = 16
BLOCK_TEXELS = 16

WEIGHTS_3BIT = np.array([0, 9, 18, 27, 37, 46, 55, 64], dtype=np.int64)
WEIGHTS_4BIT = np.array([0, 4, 9, 13, 17, 21, 26, 30, 34, 38, 43, 47, 51, 55, 60, 64], dtype=np.int64)

# Bit i set: pixel i (row-major) belongs to subset 1. Same as the first 32 BC7 two-subset partitions.
PARTITION_MASKS = np.array([
    0xCCCC, 0x8888, 0xEEEE, 0xECC8, 0xC880, 0xFEEC, 0xFEC8, 0xEC80,
    0xC800, 0xFFEC, 0xFE80, 0xE800, 0xFFE8, 0xFF00, 0xFFF0, 0xF000,
    0xF710, 0x008E, 0x7100, 0x08CE, 0x008C, 0x7310, 0x3100, 0x8CCE,
    0x088C, 0x3110, 0x6666, 0x366C, 0x17E8, 0x0FF0, 0x718E, 0x399C,
], dtype=np.int64)
# Pixel whose index is stored with one bit fewer in subset 1 (subset 0's anchor is always pixel 0).
SUBSET1_ANCHORS = np.array([
    15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15,
    15, 2, 8, 2, 2, 8, 8, 15, 2, 8, 2, 2, 8, 8, 2, 2,
], dtype=np.int64)
# (32, 16) subset of each pixel under each partition.
PARTITION_SUBSETS = (PARTITION_MASKS[:, None] >> np.arange(16)[None, :]) & 1


@dataclass(frozen=True)
class ModeSpec:
    """One BC6H mode: everything the decoder needs, described by data."""

    number: int  # Microsoft's mode number, 1..14
    code: int  # value of the mode field
    code_bits: int  # 2 or 5
    regions: int  # 1 or 2
    endpoint_bits: int  # precision of the base endpoint (and of every endpoint after the transform)
    delta_bits: tuple[int, int, int]  # stored bits of the other endpoints, per channel R, G, B
    transformed: bool  # other endpoints are deltas from endpoint 0
    layout: str  # bit layout from bit 0 upward, notation of ARB_texture_compression_bptc Table.F

    @property
    def index_bits(self) -> int:
        return 3 if self.regions == 2 else 4

    @property
    def index_start(self) -> int:
        """First bit of the index field: 82 for two-region modes, 65 for one-region modes."""
        return 128 - (46 if self.regions == 2 else 63)


MODES: tuple[ModeSpec, ...] = (
    ModeSpec(1, 0b00, 2, 2, 10, (5, 5, 5), True,
             "m[1:0],g2[4],b2[4],b3[4],r0[9:0],g0[9:0],b0[9:0],r1[4:0],g3[4],g2[3:0],"
             "g1[4:0],b3[0],g3[3:0],b1[4:0],b3[1],b2[3:0],r2[4:0],b3[2],r3[4:0],b3[3]"),
    ModeSpec(2, 0b01, 2, 2, 7, (6, 6, 6), True,
             "m[1:0],g2[5],g3[4],g3[5],r0[6:0],b3[0],b3[1],b2[4],g0[6:0],b2[5],b3[2],"
             "g2[4],b0[6:0],b3[3],b3[5],b3[4],r1[5:0],g2[3:0],g1[5:0],g3[3:0],b1[5:0],"
             "b2[3:0],r2[5:0],r3[5:0]"),
    ModeSpec(3, 0b00010, 5, 2, 11, (5, 4, 4), True,
             "m[4:0],r0[9:0],g0[9:0],b0[9:0],r1[4:0],r0[10],g2[3:0],g1[3:0],g0[10],"
             "b3[0],g3[3:0],b1[3:0],b0[10],b3[1],b2[3:0],r2[4:0],b3[2],r3[4:0],b3[3]"),
    ModeSpec(4, 0b00110, 5, 2, 11, (4, 5, 4), True,
             "m[4:0],r0[9:0],g0[9:0],b0[9:0],r1[3:0],r0[10],g3[4],g2[3:0],g1[4:0],"
             "g0[10],g3[3:0],b1[3:0],b0[10],b3[1],b2[3:0],r2[3:0],b3[0],b3[2],r3[3:0],"
             "g2[4],b3[3]"),
    ModeSpec(5, 0b01010, 5, 2, 11, (4, 4, 5), True,
             "m[4:0],r0[9:0],g0[9:0],b0[9:0],r1[3:0],r0[10],b2[4],g2[3:0],g1[3:0],"
             "g0[10],b3[0],g3[3:0],b1[4:0],b0[10],b2[3:0],r2[3:0],b3[1],b3[2],r3[3:0],"
             "b3[4],b3[3]"),
    ModeSpec(6, 0b01110, 5, 2, 9, (5, 5, 5), True,
             "m[4:0],r0[8:0],b2[4],g0[8:0],g2[4],b0[8:0],b3[4],r1[4:0],g3[4],g2[3:0],"
             "g1[4:0],b3[0],g3[3:0],b1[4:0],b3[1],b2[3:0],r2[4:0],b3[2],r3[4:0],b3[3]"),
    ModeSpec(7, 0b10010, 5, 2, 8, (6, 5, 5), True,
             "m[4:0],r0[7:0],g3[4],b2[4],g0[7:0],b3[2],g2[4],b0[7:0],b3[3],b3[4],"
             "r1[5:0],g2[3:0],g1[4:0],b3[0],g3[3:0],b1[4:0],b3[1],b2[3:0],r2[5:0],"
             "r3[5:0]"),
    ModeSpec(8, 0b10110, 5, 2, 8, (5, 6, 5), True,
             "m[4:0],r0[7:0],b3[0],b2[4],g0[7:0],g2[5],g2[4],b0[7:0],g3[5],b3[4],"
             "r1[4:0],g3[4],g2[3:0],g1[5:0],g3[3:0],b1[4:0],b3[1],b2[3:0],r2[4:0],"
             "b3[2],r3[4:0],b3[3]"),
    ModeSpec(9, 0b11010, 5, 2, 8, (5, 5, 6), True,
             "m[4:0],r0[7:0],b3[1],b2[4],g0[7:0],b2[5],g2[4],b0[7:0],b3[5],b3[4],"
             "r1[4:0],g3[4],g2[3:0],g1[4:0],b3[0],g3[3:0],b1[5:0],b2[3:0],r2[4:0],"
             "b3[2],r3[4:0],b3[3]"),
    ModeSpec(10, 0b11110, 5, 2, 6, (6, 6, 6), False,
             "m[4:0],r0[5:0],g3[4],b3[0],b3[1],b2[4],g0[5:0],g2[5],b2[5],b3[2],"
             "g2[4],b0[5:0],g3[5],b3[3],b3[5],b3[4],r1[5:0],g2[3:0],g1[5:0],g3[3:0],"
             "b1[5:0],b2[3:0],r2[5:0],r3[5:0]"),
    ModeSpec(11, 0b00011, 5, 1, 10, (10, 10, 10), False,
             "m[4:0],r0[9:0],g0[9:0],b0[9:0],r1[9:0],g1[9:0],b1[9:0]"),
    ModeSpec(12, 0b00111, 5, 1, 11, (9, 9, 9), True,
             "m[4:0],r0[9:0],g0[9:0],b0[9:0],r1[8:0],r0[10],g1[8:0],g0[10],b1[8:0],b0[10]"),
    ModeSpec(13, 0b01011, 5, 1, 12, (8, 8, 8), True,
             "m[4:0],r0[9:0],g0[9:0],b0[9:0],r1[7:0],r0[10:11],g1[7:0],g0[10:11],"
             "b1[7:0],b0[10:11]"),
    ModeSpec(14, 0b01111, 5, 1, 16, (4, 4, 4), True,
             "m[4:0],r0[9:0],g0[9:0],b0[9:0],r1[3:0],r0[10:15],g1[3:0],g0[10:15],"
             "b1[3:0],b0[10:15]"),
)
RESERVED_CODES = (0b10011, 0b10111, 0b11011, 0b11111)
MODE_10 = MODES[9]
MODE_11 = MODES[10]


def mode_spec(number: int) -> ModeSpec:
    """The ModeSpec of Microsoft's mode `number` (1..14)."""
    if not 1 <= number <= 14:
        raise ValueError(f"BC6H mode must be 1..14, got {number}")
    return MODES[number - 1]


# ---------------------------------------------------------------------------------------------
# Bit layout tables, derived once from the layout strings.

_FIELD = re.compile(r"([mrgb])(\d?)\[(\d+)(?::(\d+))?\]")
_NO_BIT = 128  # index of an always-zero column appended to the unpacked bits


@dataclass(frozen=True)
class _Layout:
    # (12, 16): block bit holding bit k of endpoint field f, or _NO_BIT. f = endpoint * 3 + channel;
    # endpoints 0, 1 are subset 0's, endpoints 2, 3 subset 1's.
    field_bits: np.ndarray
    # (P, 16, 4): block bit holding bit k of pixel i's index under partition p (P = 32 or 1), or _NO_BIT.
    index_bits: np.ndarray
    # (5,) block bits of the partition number (two-region modes only).
    partition_bits: np.ndarray


def _parse_layout(layout: str) -> list[tuple[str, int]]:
    """Expand a Table.F string into one (field, bit) per block bit, bit 0 first."""
    out: list[tuple[str, int]] = []
    for token in layout.split(","):
        match = _FIELD.fullmatch(token.strip())
        if match is None:
            raise ValueError(f"bad layout token {token!r}")
        name = match[1] + match[2]
        a = int(match[3])
        b = int(match[4]) if match[4] is not None else a
        # The block's next bit goes to value bit b, then on toward a: v[9:0] fills bits 0..9 upward,
        # and the reversed v[10:15] fills bits 15 down to 10.
        step = 1 if a >= b else -1
        out.extend((name, bit) for bit in range(b, a + step, step))
    return out


@cache
def _layout(spec: ModeSpec) -> _Layout:
    fields = np.full((12, 16), _NO_BIT, dtype=np.int64)
    for position, (name, bit) in enumerate(_parse_layout(spec.layout)):
        if name != "m":
            fields["rgb".index(name[0]) + 3 * int(name[1]), bit] = position
    q = spec.index_bits
    anchors = SUBSET1_ANCHORS if spec.regions == 2 else np.array([-1])
    index_bits = np.full((len(anchors), 16, 4), _NO_BIT, dtype=np.int64)
    for p, anchor in enumerate(anchors):
        widths = np.full(16, q)
        widths[0] -= 1
        if anchor >= 0:
            widths[anchor] -= 1
        starts = spec.index_start + np.concatenate([[0], np.cumsum(widths)[:-1]])
        for k in range(q):
            index_bits[p, k < widths, k] = starts[k < widths] + k
    partition_bits = np.arange(77, 82) if spec.regions == 2 else np.zeros(0, dtype=np.int64)
    return _Layout(fields, index_bits, partition_bits)


def _bits_to_int(gathered: np.ndarray) -> np.ndarray:
    """(..., K) bits, least significant first -> (...) int64."""
    weights = np.int64(1) << np.arange(gathered.shape[-1], dtype=np.int64)
    return (gathered.astype(np.int64) * weights).sum(-1)


def _gather_bits(bits: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """bits (n, 129) with an always-zero last column; positions (P..., K) shared by every block.
    Returns (n, P...): the integers whose bit k is bits[block, positions[..., k]]."""
    return _bits_to_int(bits[:, positions])


def _gather_bits_per_block(bits: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Like `_gather_bits` with positions (n, P..., K) chosen per block."""
    rows = np.arange(len(bits)).reshape(-1, *([1] * (positions.ndim - 1)))
    return _bits_to_int(bits[rows, positions])


# ---------------------------------------------------------------------------------------------
# Bit-exact integer pipeline (shared by the decoder and the differentiable decode's forward pass).


def _sign_extend(value: np.ndarray, bits: np.ndarray | int) -> np.ndarray:
    sign = np.int64(1) << (np.asarray(bits, dtype=np.int64) - 1)
    return (value ^ sign) - sign


# The next three functions use only arithmetic operators so that the same lines run on numpy int64
# arrays (the decoder) and torch int64 tensors (the training forward pass): one integer pipeline.


def unquantize(e, bits: int, signed: bool):
    """Expand an endpoint of `bits` precision to the 17-bit interpolation domain (Microsoft's unquantize)."""
    if not signed:
        if bits >= 15:
            return e
        out = (((e << 16) + 0x8000) >> bits) * (e != 0)
        top = e == (1 << bits) - 1
        return out + (0xFFFF - out) * top
    if bits >= 16:
        return e
    magnitude = abs(e)
    out = (((magnitude << 15) + 0x4000) >> (bits - 1)) * (magnitude != 0)
    saturated = magnitude >= (1 << (bits - 1)) - 1
    out = out + (0x7FFF - out) * saturated
    return out - 2 * out * (e < 0)


def interpolate(a, b, weight):
    """Palette entry between unquantized endpoints a and b for a 6-bit weight (0..64)."""
    return (a * (64 - weight) + b * weight + 32) >> 6


def finish_magnitude(c, signed: bool):
    """Magnitude bits (0..0x7BFF) of the half that an interpolated value c becomes (finish_unquantize).
    Its sign is c < 0 (SF16 only): the half bits are magnitude | 0x8000 for negative c, -0 included."""
    if not signed:
        return (c * 31) >> 6
    return (abs(c) * 31) >> 5


# ---------------------------------------------------------------------------------------------
# Decoder


def decode_blocks(blocks: np.ndarray, signed: bool) -> np.ndarray:
    """Decode BC6H blocks to half floats.

    blocks: (..., 16) uint8. Returns (..., 16, 3) float16 texels in row-major pixel order.
    Reserved modes decode to zero, as the format requires.
    """
    blocks = np.ascontiguousarray(blocks, dtype=np.uint8)
    if blocks.shape[-1:] != (BLOCK_BYTES,):
        raise ValueError(f"blocks must have shape (..., 16), got {blocks.shape}")
    lead = blocks.shape[:-1]
    flat = blocks.reshape(-1, BLOCK_BYTES)
    bits = np.unpackbits(flat, axis=-1, bitorder="little")
    bits = np.concatenate([bits, np.zeros((len(flat), 1), dtype=np.uint8)], axis=1)
    low2 = flat[:, 0] & 0b11
    code = np.where(low2 < 2, low2, flat[:, 0] & 0b11111)
    half_bits = np.zeros((len(flat), BLOCK_TEXELS, 3), dtype=np.uint16)
    for spec in MODES:
        selected = np.flatnonzero(code == spec.code)
        if selected.size:
            half_bits[selected] = _decode_mode(bits[selected], spec, signed)
    return half_bits.view(np.float16).reshape(*lead, BLOCK_TEXELS, 3)


def _endpoints_from_fields(raw: np.ndarray, spec: ModeSpec, signed: bool) -> np.ndarray:
    """Stored endpoint fields (n, 12) -> endpoints at full precision (n, 2*regions, 3), signed ints."""
    count = 2 * spec.regions
    raw = raw[:, : 3 * count].reshape(-1, count, 3)
    base = spec.endpoint_bits
    delta = np.array(spec.delta_bits, dtype=np.int64)
    e = raw.copy()
    if signed:
        e[:, 0] = _sign_extend(raw[:, 0], base)
    others = e[:, 1:]
    if spec.transformed or signed:
        stored_bits = delta if spec.transformed else base
        others = _sign_extend(raw[:, 1:], stored_bits)
    if spec.transformed:
        others = (others + raw[:, :1]) & ((1 << base) - 1)
        if signed:
            others = _sign_extend(others, base)
    e[:, 1:] = others
    return e


def _decode_mode(bits: np.ndarray, spec: ModeSpec, signed: bool) -> np.ndarray:
    """Half bits (n, 16, 3) of n blocks that all use `spec`."""
    layout = _layout(spec)
    endpoints = _endpoints_from_fields(_gather_bits(bits, layout.field_bits), spec, signed)
    unq = unquantize(endpoints, spec.endpoint_bits, signed)  # (n, 2R, 3)
    if spec.regions == 2:
        partition = _gather_bits(bits, layout.partition_bits)
        subset = PARTITION_SUBSETS[partition]  # (n, 16)
        index = _gather_bits_per_block(bits, layout.index_bits[partition])  # (n, 16)
    else:
        subset = np.zeros((len(bits), 16), dtype=np.int64)
        index = _gather_bits(bits, layout.index_bits[0])
    table = WEIGHTS_3BIT if spec.index_bits == 3 else WEIGHTS_4BIT
    rows = np.arange(len(bits))[:, None]
    a = unq[rows, 2 * subset]  # (n, 16, 3)
    b = unq[rows, 2 * subset + 1]
    c = interpolate(a, b, table[index][..., None])
    return (finish_magnitude(c, signed) | (0x8000 * (c < 0))).astype(np.uint16)


# ---------------------------------------------------------------------------------------------
# Encoder (every mode: bcf's trained blocks use any of them)


def _pack(spec: ModeSpec, fields: np.ndarray, index: np.ndarray, partition: np.ndarray | None) -> np.ndarray:
    """Write raw fields into blocks. fields (n, 12) unsigned stored bit patterns; index (n, 16), whose
    anchor pixels must have their top bit clear; partition (n,) or None. Returns (n, 16) uint8."""
    n = len(fields)
    layout = _layout(spec)
    bits = np.zeros((n, 129), dtype=np.uint8)
    for k in range(spec.code_bits):
        bits[:, k] = (spec.code >> k) & 1
    value_bit = np.arange(16, dtype=np.int64)
    placed = layout.field_bits != _NO_BIT  # (12, 16)
    field_values = (fields[:, :, None] >> value_bit) & 1  # (n, 12, 16)
    bits[:, layout.field_bits[placed]] = field_values[:, placed]
    if partition is not None:
        bits[:, layout.partition_bits] = (partition[:, None] >> np.arange(5)) & 1
        positions = layout.index_bits[partition]  # (n, 16, 4)
    else:
        positions = np.broadcast_to(layout.index_bits[0], (n, 16, 4))
    index_values = (index[:, :, None] >> np.arange(4)) & 1
    rows = np.broadcast_to(np.arange(n)[:, None, None], positions.shape)
    used = positions != _NO_BIT
    bits[rows[used], positions[used]] = index_values[used]
    return np.packbits(bits[:, :128], axis=-1, bitorder="little")


def _apply_anchor_rule(endpoints: np.ndarray, index: np.ndarray, subset: np.ndarray,
                       anchors: np.ndarray, index_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Swap a subset's endpoints and invert its indices where its anchor index has the top bit set.

    endpoints (n, R, 2, 3), index (n, 16), subset (n, 16), anchors (n, R) pixel of each subset's anchor.
    The decoded block is unchanged; the anchor's top bit becomes implicitly zero as the format requires.
    """
    top = 1 << (index_bits - 1)
    rows = np.arange(len(index))[:, None]
    flip = (index[rows, anchors] & top) != 0  # (n, R)
    endpoints = np.where(flip[:, :, None, None], endpoints[:, :, ::-1], endpoints)
    flip_pixel = np.take_along_axis(flip, subset, axis=1)
    index = np.where(flip_pixel, (2 * top - 1) - index, index)
    return endpoints, index


def endpoint_range(bits: int, signed: bool) -> tuple[int, int]:
    return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)


def round_endpoints(endpoints: np.ndarray, bits: int, signed: bool) -> np.ndarray:
    """Round continuous endpoints to the integers the encoder stores (ties round up), clamped to the mode's
    range. `bcf.core.fit.block_decode.quantize_endpoints` is the same rule on torch tensors (training)."""
    low, high = endpoint_range(bits, signed)
    return np.floor(np.clip(endpoints, low, high) + 0.5).astype(np.int64)


def _check_int_range(name: str, values: np.ndarray, low: int, high: int) -> np.ndarray:
    values = np.asarray(values)
    if not np.issubdtype(values.dtype, np.integer):
        raise TypeError(f"{name} must be integers, got {values.dtype}")
    if values.size and (values.min() < low or values.max() > high):
        raise ValueError(f"{name} must lie in [{low}, {high}], got [{values.min()}, {values.max()}]")
    return values.astype(np.int64)


def delta_window(spec: ModeSpec) -> tuple[np.ndarray, np.ndarray]:
    """Per channel (3,) lowest and highest difference `endpoint - endpoint 0` that a transformed mode's stored
    deltas can hold (signed, `spec.delta_bits` wide). Non-transformed modes store every endpoint in full: the
    window is the whole endpoint range."""
    if not spec.transformed:
        width = np.int64(1) << spec.endpoint_bits
        return np.full(3, -width, dtype=np.int64), np.full(3, width, dtype=np.int64)
    half = np.int64(1) << (np.array(spec.delta_bits, dtype=np.int64) - 1)
    return -half, half - 1


def encode_blocks(mode: int, endpoints: np.ndarray, index: np.ndarray, partition: np.ndarray | None,
                  signed: bool) -> np.ndarray:
    """Encode blocks of one BC6H mode (1..14).

    endpoints: (n, R, 2, 3) ints, [block, subset, endpoint, channel] (R = the mode's regions), the endpoints the
        decoder is to reconstruct, at the mode's endpoint precision: 0 .. 2^b - 1 (UF16) or -2^(b-1) ..
        2^(b-1) - 1 (SF16). Transformed modes (1-9, 12-14) store endpoint 0 in full and the others as deltas
        from it, so every other endpoint must lie within `delta_window(spec)` of endpoint 0 as stored, i.e.
        after the anchor rule below has swapped subset 0's endpoints where it had to.
    index: (n, 16) ints 0 .. 2^q - 1 per pixel (row-major); partition: (n,) ints 0..31 for two-region modes,
        None for one-region modes. Subset 1 holds the pixels whose bit is set in PARTITION_MASKS[partition].
    Returns (n, 16) uint8 blocks that decode to exactly these parameters (a subset's endpoints are swapped and
    its indices inverted where the anchor's index has its top bit set, as the format requires).
    """
    spec = mode_spec(mode)
    low, high = endpoint_range(spec.endpoint_bits, signed)
    endpoints = _check_int_range("endpoints", endpoints, low, high)
    index = _check_int_range("index", index, 0, (1 << spec.index_bits) - 1)
    n = len(index)
    regions = spec.regions
    if endpoints.shape != (n, regions, 2, 3) or index.shape != (n, 16):
        raise ValueError(f"mode {mode}: expected endpoints ({n}, {regions}, 2, 3) and index ({n}, 16); got "
                         f"{endpoints.shape}, {index.shape}")
    if regions == 2:
        if partition is None:
            raise ValueError(f"mode {mode} has two regions: it needs a partition")
        partition = _check_int_range("partition", partition, 0, 31)
        if partition.shape != (n,):
            raise ValueError(f"expected partition ({n},), got {partition.shape}")
        subset = PARTITION_SUBSETS[partition]
        anchors = np.stack([np.zeros(n, dtype=np.int64), SUBSET1_ANCHORS[partition]], axis=1)
    else:
        partition = None
        subset = np.zeros((n, 16), dtype=np.int64)
        anchors = np.zeros((n, 1), dtype=np.int64)
    endpoints, index = _apply_anchor_rule(endpoints, index, subset, anchors, spec.index_bits)
    flat = endpoints.reshape(n, 2 * regions, 3)
    fields = np.zeros((n, 4, 3), dtype=np.int64)
    fields[:, 0] = flat[:, 0] & ((1 << spec.endpoint_bits) - 1)  # two's complement for SF16
    if spec.transformed:
        deltas = flat[:, 1:] - flat[:, :1]
        lowest, highest = delta_window(spec)
        outside = (deltas < lowest) | (deltas > highest)
        if outside.any():
            raise ValueError(f"mode {mode}: {int(outside.any(axis=(1, 2)).sum())} blocks have endpoints outside the "
                             f"delta window [{lowest.tolist()}, {highest.tolist()}] of endpoint 0")
        fields[:, 1:2 * regions] = deltas & ((np.int64(1) << np.array(spec.delta_bits, dtype=np.int64)) - 1)
    else:
        fields[:, 1:2 * regions] = flat[:, 1:] & ((1 << spec.endpoint_bits) - 1)
    return _pack(spec, fields.reshape(n, 12), index, partition)


def encode_mode10(endpoints: np.ndarray, index: np.ndarray, partition: np.ndarray, signed: bool) -> np.ndarray:
    """Encode two-region mode-10 blocks: `encode_blocks(10, ...)`, 6-bit endpoints (n, 2, 2, 3) stored in full,
    3-bit indices (n, 16), partitions (n,)."""
    return encode_blocks(10, endpoints, index, partition, signed)


def encode_mode11(endpoints: np.ndarray, index: np.ndarray, signed: bool) -> np.ndarray:
    """Encode one-region mode-11 blocks: `encode_blocks(11, ...)` with 10-bit endpoints (n, 2, 3) stored in
    full and 4-bit indices (n, 16)."""
    return encode_blocks(11, np.asarray(endpoints)[:, None], index, None, signed)


# ---------------------------------------------------------------------------------------------
# Images <-> blocks


def image_to_block_texels(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) -> (ceil(h/4), ceil(w/4), 16, 3) texels per block, padding by repeating the last row/column."""
    h, w, channels = image.shape
    bh, bw = -(-h // 4), -(-w // 4)
    padded = np.pad(image, ((0, 4 * bh - h), (0, 4 * bw - w), (0, 0)), mode="edge")
    return padded.reshape(bh, 4, bw, 4, channels).transpose(0, 2, 1, 3, 4).reshape(bh, bw, 16, channels)


def block_texels_to_image(texels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(bh, bw, 16, C) -> (height, width, C), cropping the padding of partial blocks."""
    bh, bw, _, channels = texels.shape
    image = texels.reshape(bh, bw, 4, 4, channels).transpose(0, 2, 1, 3, 4).reshape(4 * bh, 4 * bw, channels)
    return image[:height, :width]


def decode_image(blocks: np.ndarray, width: int, height: int, signed: bool) -> np.ndarray:
    """Decode one texture level: blocks (ceil(h/4), ceil(w/4), 16) uint8 -> (height, width, 3) float16."""
    return block_texels_to_image(decode_blocks(blocks, signed), width, height)


def mode_for_regions(regions: int) -> ModeSpec:
    if regions not in (1, 2):
        raise ValueError(f"endpoints must have 1 (mode 11) or 2 (mode 10) regions, got {regions}")
    return MODE_10 if regions == 2 else MODE_11


# ---------------------------------------------------------------------------------------------
# Half bits <-> values and the continuous endpoint domain (inverse of paper eq. 9)


def value_to_half_bits(x: np.ndarray, signed: bool) -> np.ndarray:
    """Inverse of eq. 9 for real values: a continuous (float64) half-bit coordinate in which BC6H
    interpolates linearly. Unsigned values are clamped to [0, 65504]; signed ones to [-65504, 65504]
    and returned as sign * magnitude bits."""
    x = np.asarray(x, dtype=np.float64)
    low = -65504.0 if signed else 0.0
    x = np.clip(np.nan_to_num(x, nan=0.0), low, 65504.0)
    magnitude = np.abs(x)
    exponent = np.clip(np.floor(np.log2(np.maximum(magnitude, 2.0**-24))), -14, 15)
    # Normal halves: v = 1024 * (e + 15) + 1024 * (m / 2^e - 1); subnormals: v = m * 2^24.
    normal = 1024.0 * (exponent + 15.0) + 1024.0 * (magnitude / np.exp2(exponent) - 1.0)
    v = np.where(magnitude < 2.0**-14, magnitude * 2.0**24, normal)
    return np.sign(x) * v


def half_bits_to_endpoint_continuous(v: np.ndarray, bits: int, signed: bool) -> np.ndarray:
    """Continuous endpoint (clamped to the endpoint range) whose unquantize + finish, used alone (weight 0),
    gives half-bit coordinate v: the inverse of eq. 7 with the finish applied, i.e. of
    UF16 v = 31/64 * (e * 2^16 + 2^15) / 2^b and SF16 |v| = 31/32 * (|e| * 2^15 + 2^14) / 2^(b-1)."""
    v = np.asarray(v, dtype=np.float64)
    if not signed:
        e = (v * 64.0 / 31.0 * 2.0**bits - 32768.0) / 65536.0
        return np.clip(e, 0.0, 2.0**bits - 1.0)
    magnitude = (np.abs(v) * 32.0 / 31.0 * 2.0 ** (bits - 1) - 16384.0) / 32768.0
    limit = 2.0 ** (bits - 1) - 1.0
    return np.sign(v) * np.clip(magnitude, 0.0, limit)


