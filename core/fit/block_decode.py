"""The differentiable BC6H decode used for training (paper eq. 7-9): exact integer forward pass, straight-
through rounding and the continuous unquantize / interpolate / finish of eq. 7-8 plus the slope of eq. 9
backward. Its forward result equals `bcf.core.codec.bc6h.decode_blocks` of the blocks export writes, bit for bit.
"""

from __future__ import annotations

import torch

from bcf.core.codec.bc6h import (PARTITION_SUBSETS, WEIGHTS_3BIT, WEIGHTS_4BIT, endpoint_range, finish_magnitude,
                                 interpolate, mode_for_regions, unquantize)

__all__ = ["decode_blocks_differentiable", "decode_level_one_region", "half_bits_to_value", "quantize_endpoints",
           "quantize_weights"]


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
    it (`decode_level_one_region` is the same in closed form for the default mode).
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


def decode_level_one_region(endpoints: torch.Tensor, weights: torch.Tensor, blocks_high: int,
                            blocks_wide: int) -> torch.Tensor:
    """`decode_blocks_differentiable` for mode 11, UF16 (the default presets' blocks), returning the whole
    level as an image: endpoints (bh * bw, 1, 2, 3), weights (bh * bw, 16), blocks row-major over the level,
    pixels row-major in a block -> (3, 4 bh, 4 bw). Same values bit for bit and the same gradients (up to
    float rounding order); tests/test_bc6h.py compares the two."""
    return _OneRegionLevelDecode.apply(endpoints, weights, blocks_high, blocks_wide)


def _block_sums(x: torch.Tensor) -> torch.Tensor:
    """(3, bh, 4, bw, 4) image-layout values -> (3, bh, bw) sums over each block's 16 pixels. A matrix product
    for the 4 contiguous pixels of a block row is several times faster than torch's reduction over a size-4
    innermost dimension."""
    c, bh, _, bw, _ = x.shape
    ones = torch.ones((4, 1), dtype=x.dtype, device=x.device)
    return (x.reshape(-1, 4) @ ones).view(c, bh, 4, bw).sum(2)


class _OneRegionLevelDecode(torch.autograd.Function):
    """Forward and backward in closed form, computed straight in image layout (3, bh, 4, bw, 4): the
    broadcast of per-block endpoints against per-pixel weights does the block-to-image transpose for free,
    the integer pipeline runs in int32 in place, and the half bits become values by reinterpretation. Only
    the output is kept for the backward (the slope of eq. 9 is read from its exponent)."""

    @staticmethod
    def forward(ctx, endpoints: torch.Tensor, weights: torch.Tensor, blocks_high: int,
                blocks_wide: int) -> torch.Tensor:
        bh, bw = blocks_high, blocks_wide
        e_round = quantize_endpoints(endpoints, 10, False).view(bh, bw, 2, 3)
        index = quantize_weights(weights, 4).view(bh, bw, 4, 4).permute(0, 2, 1, 3)  # (bh, 4, bw, 4)
        e_int = e_round.to(torch.int32)
        # `unquantize` of 10-bit UF16 endpoints: 0 stays 0, 1023 saturates to 0xFFFF, else e * 64 + 32.
        ends = torch.where(e_int >= 1023, 0xFFFF, torch.where(e_int > 0, e_int * 64 + 32, 0))
        ends = ends.permute(3, 0, 2, 1).unsqueeze(-1)  # (3, bh, 2, bw, 1)
        first, second = ends[:, :, 0:1], ends[:, :, 1:2]  # (3, bh, 1, bw, 1)
        table = torch.as_tensor(WEIGHTS_4BIT, dtype=torch.int32, device=endpoints.device)
        weight = table[index.long()]  # (bh, 4, bw, 4)
        # `interpolate`: (a (64 - w) + b w + 32) >> 6 = (64 a + 32 + (b - a) w) >> 6; then `finish_magnitude`.
        c = torch.empty((3, bh, 4, bw, 4), dtype=torch.int32, device=endpoints.device)  # image layout
        torch.addcmul(first * 64 + 32, second - first, weight, out=c).bitwise_right_shift_(6)
        magnitude = c.mul_(31).bitwise_right_shift_(6)  # half bits 0..0x7BFF
        value = magnitude.to(torch.int16).view(torch.float16).to(torch.float32).view(3, 4 * bh, 4 * bw)
        ctx.save_for_backward(value, index, e_round)
        return value

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        value, index, e_round = ctx.saved_tensors
        bh, bw = e_round.shape[:2]
        # Eq. 9's slope d value / d bits is the half's spacing at the value: 2^(exponent - 10), and 2^-24
        # for subnormals and zero. Times 31/64 (the finish) it is d value / d c; the constants are applied to
        # the per-block sums below, not to every texel.
        power = (value.view(torch.int32) & 0x7F800000).view(torch.float32).clamp_(min=2.0 ** -14)
        d_c = (grad * power).view(3, bh, 4, bw, 4)
        w = index / 15.0  # the straight-through weights' forward value, (bh, 4, bw, 4)
        # c = a + (b - a) w with a, b = e * 2^6 + 2^5 (eq. 7, continuous): straight-through to the parameters.
        d_second = _block_sums(d_c * w)  # (3, bh, bw)
        d_first = _block_sums(d_c) - d_second
        scale = 64.0 * 31.0 / 64.0 / 1024.0  # d a / d e = 64, times the constants of the slope
        d_ends = torch.stack([d_first, d_second], -1).permute(1, 2, 3, 0).reshape(bh * bw, 1, 2, 3) * scale
        span = (e_round[..., 1, :] - e_round[..., 0, :]).permute(2, 0, 1)[:, :, None, :, None]  # (b - a) / 64
        d_weights = (d_c * span).sum(0).permute(0, 2, 1, 3).reshape(bh * bw, 16) * scale
        return d_ends, d_weights, None, None
