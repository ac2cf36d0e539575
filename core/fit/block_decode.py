"""The differentiable BC6H decode used for training (paper eq. 7-9): exact integer forward pass, straight-
through rounding and the continuous unquantize / interpolate / finish of eq. 7-8 plus the slope of eq. 9
backward. Its forward result equals `bcf.core.codec.bc6h.decode_blocks` of the blocks export writes, bit for bit.
"""

from __future__ import annotations

import torch

from bcf.core.codec.bc6h import (PARTITION_SUBSETS, WEIGHTS_3BIT, WEIGHTS_4BIT, endpoint_range, finish_magnitude,
                                 interpolate, mode_for_regions, unquantize)

__all__ = ["decode_blocks_differentiable", "half_bits_to_value", "quantize_endpoints", "quantize_weights"]


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
    unquantize/interpolate/finish of eq. 7-8 (without floors), then the exact slope of eq. 9.
    """
    spec = mode_for_regions(endpoints.shape[-3])
    if spec.regions == 1 and not signed:
        return _OneRegionDecode.apply(endpoints, weights)
    return _decode_autograd(endpoints, weights, partition, signed)


def _decode_autograd(endpoints: torch.Tensor, weights: torch.Tensor, partition: torch.Tensor | None,
                     signed: bool) -> torch.Tensor:
    """`decode_blocks_differentiable` for any mode, its backward left to autograd."""
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




class _OneRegionDecode(torch.autograd.Function):
    """Mode 11, UF16 (the default preset's blocks): the forward and backward of `_decode_autograd` in closed
    form, so no (n, 16, 3) intermediate is kept for autograd but the slope of eq. 9. Same values, same
    gradients (up to float rounding order); tests/test_bc6h.py compares the two."""

    @staticmethod
    def forward(ctx, endpoints: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """endpoints (..., 1, 2, 3), weights (..., 16) -> (..., 16, 3) texel values."""
        e_round = quantize_endpoints(endpoints, 10, False)
        index = quantize_weights(weights, 4)
        # The decoder's integer pipeline (`unquantize`, `interpolate`, `finish_magnitude`) in float32, where
        # every intermediate is an integer below 2^24 and so exact: half the memory traffic of int64.
        ends = torch.where(e_round >= 1023.0, 65535.0, torch.where(e_round > 0, e_round * 64.0 + 32.0, 0.0))
        weight = torch.as_tensor(WEIGHTS_4BIT, dtype=torch.float32, device=endpoints.device)[index.long()]
        weight = weight.unsqueeze(-1)  # (..., 16, 1)
        c = torch.floor((ends[..., 0, 0:1, :] * (64.0 - weight) + ends[..., 0, 1:2, :] * weight + 32.0) / 64.0)
        magnitude = torch.floor(c * (31.0 / 64.0))  # exact: c * 31 < 2^24, and / 64 is exact
        exponent = torch.clamp(torch.floor(magnitude / 1024.0) - 1.0, min=0.0)  # h(v) of eq. 9
        scale = torch.exp2(exponent - 14.0)
        # The surrogate's slope: d value / d c = 2^(h-14) / 1024 (eq. 9) * 31/64 (finish), eq. 7-8 for the rest.
        ctx.save_for_backward(scale, index, e_round)
        return scale * (magnitude / 1024.0 - exponent)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        scale, index, e_round = ctx.saved_tensors
        d_c = grad * scale * (31.0 / 64.0 / 1024.0)  # (..., 16, 3)
        w = (index / 15.0).unsqueeze(-1)  # the straight-through weights' forward value
        # c = a + (b - a) w with a, b = e * 2^6 + 2^5 (eq. 7, continuous): straight-through to the parameters.
        d_second = (d_c * w).sum(-2)
        d_first = d_c.sum(-2) - d_second
        span = (e_round[..., 0, 1, :] - e_round[..., 0, 0, :]).unsqueeze(-2)  # (b - a) / 64
        return torch.stack([d_first, d_second], -2).unsqueeze(-3) * 64.0, (d_c * span).sum(-1) * 64.0
