"""The differentiable BC6H decode used for training (paper eq. 7-9): exact integer forward pass, straight-
through rounding and the continuous unquantize / interpolate / finish of eq. 7-8 plus the slope of eq. 9
backward. Its forward result equals `bcf.core.codec.bc6h.decode_blocks` of the blocks export writes, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bcf.core.codec.bc6h import (MODES, PARTITION_SUBSETS, WEIGHTS_3BIT, WEIGHTS_4BIT, delta_window, endpoint_range,
                                 finish_magnitude, interpolate, mode_for_regions, unquantize)

__all__ = ["BlockModes", "decode_blocks_differentiable", "decode_level", "half_bits_to_value", "quantize_blocks",
           "quantize_endpoints", "quantize_weights"]


def half_bits_to_value(v: torch.Tensor) -> torch.Tensor:
    """Paper eq. 9: the value of the half whose bit pattern is the magnitude v (0..0x7BFF), as a
    piecewise-linear function of v. Exact in float32 at integer v; differentiable in v."""
    exponent = torch.clamp(torch.floor(v.detach() / 1024.0) - 1.0, min=0.0)  # h(v) of eq. 9
    return torch.exp2(exponent - 14.0) * (v / 1024.0 - exponent)


def quantize_endpoints(endpoints: torch.Tensor, bits: int, signed: bool) -> torch.Tensor:
    """Round continuous endpoints to the integers the encoder stores (ties round up), clamped to the
    mode's range: `bcf.core.codec.bc6h.round_endpoints` on tensors. Training and export round through it."""
    low, high = endpoint_range(bits, signed)
    return torch.floor(endpoints.clamp(low, high) + 0.5)


def quantize_weights(weights: torch.Tensor, index_bits: int) -> torch.Tensor:
    """Round weights in [0, 1] to index values 0 .. 2^q - 1 (as floats)."""
    top = (1 << index_bits) - 1
    return torch.floor(weights.clamp(0.0, 1.0) * top + 0.5)


def _per_pixel_endpoints(endpoints: torch.Tensor, subset: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """endpoints (..., R, 2, 3) -> the two endpoints (..., 16, 3) of every pixel's subset."""
    if subset is None:
        first = endpoints[..., 0, 0, :].unsqueeze(-2).expand(*endpoints.shape[:-3], 16, 3)
        second = endpoints[..., 0, 1, :].unsqueeze(-2).expand(*endpoints.shape[:-3], 16, 3)
        return first, second
    flat = endpoints.flatten(-3, -2)  # (..., 2R, 3): subset s has endpoints 2s, 2s + 1
    gather = (2 * subset).unsqueeze(-1).expand(*subset.shape, 3)
    return torch.gather(flat, -2, gather), torch.gather(flat, -2, gather + 1)


def decode_blocks_differentiable(endpoints: torch.Tensor, weights: torch.Tensor,
                                 partition: torch.Tensor | None, signed: bool) -> torch.Tensor:
    """BC6H decode of explicit-endpoint blocks as a differentiable torch function.

    endpoints: (..., R, 2, 3) float, continuous endpoints in the stored integer domain. R = 2 means mode 10
        (6-bit endpoints: 0..63 UF16, -32..31 SF16; 3-bit indices), R = 1 mode 11 (10-bit; 4-bit indices).
    weights: (..., 16) float in [0, 1], position of each pixel on its segment (alpha of eq. 6).
    partition: (...,) int64 in 0..31 for R = 2 (subset 1 = set bits of PARTITION_MASKS), None for R = 1.
    Returns (..., 16, 3) float32 texel values.

    Forward: rounds endpoints and weights (`quantize_endpoints`, `quantize_weights`) and runs the decoder's
    integer pipeline, so the result equals, bit for bit, `decode_blocks` of the blocks `encode_mode10/11`
    writes from the rounded parameters. Backward: straight-through rounding and the continuous
    unquantize/interpolate/finish of eq. 7-8 (without floors), then the exact slope of eq. 9; autograd derives
    it. Training uses `decode_level`, the same in closed form for levels of any modes; this path is its
    reference in the tests.
    """
    spec = mode_for_regions(endpoints.shape[-3])
    bits, q = spec.endpoint_bits, spec.index_bits
    device = endpoints.device
    subset = None
    if spec.regions == 2:
        if partition is None:
            raise ValueError("mode 10 (two regions) needs a partition")
        subset = torch.as_tensor(PARTITION_SUBSETS, device=device)[partition]

    e_round = quantize_endpoints(endpoints, bits, signed)
    index = quantize_weights(weights, q)
    e_st = endpoints + (e_round - endpoints).detach()  # straight-through rounding
    w_st = weights + (index / ((1 << q) - 1) - weights).detach()

    # Exact forward: the decoder's integer pipeline on the rounded parameters.
    e_int = e_round.detach().to(torch.int64)
    table = torch.as_tensor(WEIGHTS_3BIT if q == 3 else WEIGHTS_4BIT, device=device)
    a_int, b_int = _per_pixel_endpoints(unquantize(e_int, bits, signed), subset)
    c = interpolate(a_int, b_int, table[index.detach().to(torch.int64)].unsqueeze(-1))
    magnitude_exact = finish_magnitude(c, signed).to(torch.float32)

    # Surrogate for the gradient: eq. 7 (unquantize, the 31/64 or 31/32 finish applied after) and eq. 8.
    if signed:
        unq = e_st * 2.0 ** (16 - bits) + torch.sign(e_st.detach()) * 2.0 ** (15 - bits)
    else:
        unq = e_st * 2.0 ** (16 - bits) + 2.0 ** (15 - bits)
    a, b = _per_pixel_endpoints(unq, subset)
    c_cont = a + (b - a) * w_st.unsqueeze(-1)
    magnitude_cont = c_cont.abs() * (31.0 / 32.0) if signed else c_cont * (31.0 / 64.0)
    magnitude = magnitude_exact + (magnitude_cont - magnitude_cont.detach())

    value = half_bits_to_value(magnitude)  # eq. 9, exact at the integer forward value
    return torch.where(c < 0, -value, value) if signed else value


# ------------------------------------------------------------------------------ levels of mixed modes
# Every block of a level may use its own BC6H mode (UF16). A block is held as two segments (n, 2, 2, 3) of
# continuous endpoints in its mode's endpoint units, 16 continuous weights in [0, 1] and a partition; a
# one-region block uses segment 0 for all its pixels.

_WINDOW = np.array([delta_window(spec) for spec in MODES], dtype=np.int64)  # (14, 2, 3) per mode: low, high
_BITS = np.array([spec.endpoint_bits for spec in MODES], dtype=np.int64)
_INDEX_TOP = np.array([(1 << spec.index_bits) - 1 for spec in MODES], dtype=np.int64)
_TWO_REGIONS = np.array([spec.regions == 2 for spec in MODES])
_WEIGHT_TABLE = np.concatenate([WEIGHTS_3BIT, WEIGHTS_4BIT])  # 3-bit indices at 0..7, 4-bit ones at 8..23


@dataclass(frozen=True)
class BlockModes:
    """What a level's blocks are, per block, as tensors on the training device: endpoint bits (n,), top index
    (7 or 15) (n,), the delta window of endpoint 0 (n, 2, 3) (the whole range where the mode stores every
    endpoint), each pixel's subset (n, 16) (zeros for one-region blocks), and whether any block has two."""

    bits: torch.Tensor
    index_top: torch.Tensor
    window: torch.Tensor
    subset: torch.Tensor
    two_regions: bool

    @classmethod
    def of(cls, mode: torch.Tensor, partition: torch.Tensor) -> "BlockModes":
        """From per-block Microsoft mode numbers (n,) and partitions (n,) (ignored for one-region modes)."""
        device = mode.device
        row = (mode.long() - 1).cpu().numpy()
        two = _TWO_REGIONS[row]
        subset = torch.as_tensor(PARTITION_SUBSETS, device=device)[partition.long()]
        subset = subset * torch.as_tensor(two, device=device)[:, None]
        return cls(torch.as_tensor(_BITS[row], device=device), torch.as_tensor(_INDEX_TOP[row], device=device),
                   torch.as_tensor(_WINDOW[row], device=device), subset, bool(two.any()))

    @property
    def top(self) -> torch.Tensor:
        """Largest endpoint (n,): 2^bits - 1."""
        return (1 << self.bits) - 1


def quantize_blocks(endpoints: torch.Tensor, weights: torch.Tensor,
                    modes: BlockModes) -> tuple[torch.Tensor, torch.Tensor]:
    """The integers a level's blocks store: endpoints (n, 2, 2, 3) int64 and indices (n, 16) int64, from
    continuous endpoints in each block's endpoint units and weights in [0, 1]. Both round to nearest (ties up)
    and clamp to their ranges; then every endpoint is clamped into the delta window of the endpoint the encoder
    stores first: subset 0's second end when pixel 0's index has its top bit set (the anchor rule swaps the
    segment), else its first. Training's forward pass and the export both quantise through this function, so
    the trained texels are the exported ones."""
    top = modes.top[:, None, None, None]
    rounded = torch.minimum(torch.floor(endpoints.detach().clamp(min=0.0) + 0.5).long(), top)
    index = torch.floor(weights.detach().clamp(0.0, 1.0) * modes.index_top[:, None] + 0.5).long()
    flipped = index[:, 0] > modes.index_top // 2
    base = torch.where(flipped[:, None], rounded[:, 0, 1], rounded[:, 0, 0])[:, None, None]  # (n, 1, 1, 3)
    low = (base + modes.window[:, None, None, 0]).clamp(min=0)
    high = torch.minimum(base + modes.window[:, None, None, 1], top)
    return torch.maximum(torch.minimum(rounded, high), low), index


def _unquantize(e: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
    """`bc6h.unquantize` (UF16) with per-block bits (broadcast against e): 0 stays 0, the top value saturates to
    0xFFFF, 16-bit endpoints are used as they are, else ((e << 16) + 0x8000) >> bits."""
    shifted = ((e << 16) + 0x8000) >> bits
    shifted = torch.where(e == 0, 0, torch.where(e == (1 << bits) - 1, 0xFFFF, shifted))
    return torch.where(bits >= 15, e, shifted)


def decode_level(endpoints: torch.Tensor, weights: torch.Tensor, modes: BlockModes, blocks_high: int,
                 blocks_wide: int) -> torch.Tensor:
    """Decode a level of blocks of any modes (UF16) into its image (3, 4 bh, 4 bw), differentiably.

    endpoints (bh * bw, 2, 2, 3) continuous in each block's endpoint units, weights (bh * bw, 16) in [0, 1],
    blocks row-major over the level, pixels row-major in a block. Forward: `quantize_blocks`, then the decoder's
    integer pipeline, bit for bit what `bc6h.decode_blocks` gives for the encoded blocks. Backward: straight
    through the rounding and clamps, the continuous unquantize / interpolate / finish of eq. 7-8 and the slope
    of eq. 9, in closed form (tests/test_bc6h.py compares it with autograd through
    `decode_blocks_differentiable`)."""
    return _LevelDecode.apply(endpoints, weights, modes, blocks_high, blocks_wide)


def _block_sums(x: torch.Tensor) -> torch.Tensor:
    """(3, bh, 4, bw, 4) image-layout values -> (3, bh, bw) sums over each block's 16 pixels. A matrix product
    for the 4 contiguous pixels of a block row is several times faster than torch's reduction over a size-4
    innermost dimension."""
    c, bh, _, bw, _ = x.shape
    ones = torch.ones((4, 1), dtype=x.dtype, device=x.device)
    return (x.reshape(-1, 4) @ ones).view(c, bh, 4, bw).sum(2)


def _image_layout(per_pixel: torch.Tensor, bh: int, bw: int) -> torch.Tensor:
    """(bh * bw, 16) per-pixel values of row-major blocks -> (bh, 4, bw, 4), the level's image layout."""
    return per_pixel.view(bh, bw, 4, 4).permute(0, 2, 1, 3)


def _per_block(x: torch.Tensor, bh: int, bw: int) -> torch.Tensor:
    """(bh * bw, ..., 3) per-block values -> (3, ..., bh, 1, bw, 1): broadcasts against image-layout pixels."""
    x = x.view(bh, bw, *x.shape[1:])
    x = x.permute(-1, *range(2, x.dim() - 1), 0, 1).contiguous()
    return x[..., :, None, :, None]


class _LevelDecode(torch.autograd.Function):
    """Forward and backward in closed form, computed straight in image layout (3, bh, 4, bw, 4): per-block
    values (3, bh, 1, bw, 1) broadcast against per-pixel weights (bh, 4, bw, 4) (the broadcast does the
    block-to-image transpose), the integer pipeline in int32, and the half bits become values by
    reinterpretation. A pixel of a block's second subset takes segment 1's values (a select, only in levels
    that have two-region blocks). Only the output, the indices, the subsets and the rounded endpoints are kept
    for the backward (eq. 9's slope is read from the output)."""

    @staticmethod
    def forward(ctx, endpoints: torch.Tensor, weights: torch.Tensor, modes: BlockModes, blocks_high: int,
                blocks_wide: int) -> torch.Tensor:
        bh, bw = blocks_high, blocks_wide
        e_round, index = quantize_blocks(endpoints, weights, modes)
        ends = _per_block(_unquantize(e_round, modes.bits[:, None, None, None]).to(torch.int32), bh, bw)
        low, span = ends[:, :, 0] * 64 + 32, ends[:, :, 1] - ends[:, :, 0]  # (3, 2, bh, 1, bw, 1) per segment
        table = torch.as_tensor(_WEIGHT_TABLE, dtype=torch.int32, device=endpoints.device)
        offset = torch.where(modes.index_top == 7, 0, 8)[:, None]
        weight = _image_layout(table[index + offset], bh, bw).contiguous()  # (bh, 4, bw, 4)
        if modes.two_regions:  # segment 0's values plus subset (0 or 1) times the difference (faster than a select)
            second = _image_layout(modes.subset, bh, bw).to(torch.int32).contiguous()
            low = torch.addcmul(low[:, 0], second, low[:, 1] - low[:, 0])
            span = torch.addcmul(span[:, 0], second, span[:, 1] - span[:, 0])
        else:
            low, span = low[:, 0], span[:, 0]
        # `interpolate`: (a (64 - w) + b w + 32) >> 6 = (64 a + 32 + (b - a) w) >> 6; then `finish_magnitude`.
        c = torch.addcmul(low, span, weight).bitwise_right_shift_(6)  # (3, bh, 4, bw, 4)
        magnitude = c.mul_(31).bitwise_right_shift_(6)  # half bits 0..0x7BFF
        value = magnitude.to(torch.int16).view(torch.float16).to(torch.float32).view(3, 4 * bh, 4 * bw)
        ctx.two_regions = modes.two_regions
        ctx.save_for_backward(value, index, e_round, modes.bits, modes.index_top, modes.subset)
        return value

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        value, index, e_round, bits, index_top, subset = ctx.saved_tensors
        n = e_round.shape[0]
        bh, bw = value.shape[1] // 4, value.shape[2] // 4
        # Eq. 9's slope d value / d bits is the half's spacing at the value: 2^(exponent - 10), and 2^-24
        # for subnormals and zero; times 31/64 (the finish) it is d value / d c. The constant 2^-10 * 31/64
        # and the per-block 2^(16 - bits) (d c / d e, eq. 7) are applied per block below.
        power = (value.view(torch.int32) & 0x7F800000).view(torch.float32).clamp_(min=2.0 ** -14)
        d_c = (grad * power).view(3, bh, 4, bw, 4)
        t = _image_layout(index / index_top[:, None].to(torch.float32), bh, bw).contiguous()  # straight-through
        d_b = d_c * t  # c = a + (b - a) t: b gets t, a gets 1 - t
        sums_c, sums_b = _block_sums(d_c), _block_sums(d_b)  # (3, bh, bw)
        scale = torch.exp2(16.0 - bits.to(torch.float32)) * (31.0 / 64.0 / 1024.0)  # (n,)
        span = (e_round[:, :, 1] - e_round[:, :, 0]).to(torch.float32) * scale[:, None, None]  # (n, 2, 3)
        span = _per_block(span, bh, bw)  # (3, 2, bh, 1, bw, 1)
        d_weights = d_c * span[:, 0]
        if ctx.two_regions:  # sums over subset 1 alone; subset 0's are the rest
            d_c1 = d_c * _image_layout(subset, bh, bw).to(torch.float32).contiguous()
            sums_c1, sums_b1 = _block_sums(d_c1), _block_sums(d_c1 * t)
            d_weights += d_c1 * (span[:, 1] - span[:, 0])
        else:
            sums_c1 = sums_b1 = torch.zeros_like(sums_c)
        d_ends = torch.stack([sums_c - sums_c1 - sums_b + sums_b1, sums_b - sums_b1,
                              sums_c1 - sums_b1, sums_b1])  # (segment 0 a, b, segment 1 a, b) x (3, bh, bw)
        d_endpoints = d_ends.view(2, 2, 3, n).permute(3, 0, 1, 2) * scale[:, None, None, None]
        d_weights = d_weights.sum(0).permute(0, 2, 1, 3).reshape(n, 16)
        return d_endpoints, d_weights, None, None, None
