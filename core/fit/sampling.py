"""Texture filtering in torch: bilinear and bicubic lookups with wrap or clamp addressing, trilinear
sampling of a mip pyramid (paper eq. 10), and the filtered reference material F(M)(u, v, s) (paper §5.1).

Conventions used everywhere in bcf:
- uv: (N, 2) float32, u across the width, v down the rows, [0, 1) covers the texture once. Texel (x, y) of a
  w x h level covers [x/w, (x+1)/w) x [y/h, (y+1)/h); its centre is ((x + 0.5)/w, (y + 0.5)/h), as in
  OpenGL and Direct3D.
- Images are (C, h, w) float32 tensors (channels first, as torch's grid_sample wants).
- Scale s: the mip level of the material a lookup corresponds to (0 = full resolution). One s per call.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from bcf.core.material import images
from bcf.core.options import Address

__all__ = ["Address", "ReferenceMaterial", "material_mip_count", "sample_bicubic", "sample_bilinear",
           "sample_trilinear", "texel_centres", "trilinear_levels"]

_BICUBIC_PAD = 2  # texels a bicubic tap reaches beyond the sample's own texel


def _wrap_grid(uv: torch.Tensor, w: int, h: int, pad: int) -> torch.Tensor:
    """grid_sample coordinates (align_corners=False) of uv in a w x h image circularly padded by `pad`."""
    uv = uv - torch.floor(uv)
    scale = torch.tensor([w / (w + 2 * pad), h / (h + 2 * pad)], dtype=uv.dtype, device=uv.device)
    offset = torch.tensor([pad / (w + 2 * pad), pad / (h + 2 * pad)], dtype=uv.dtype, device=uv.device)
    return (uv * scale + offset) * 2.0 - 1.0


def _grid_sample(batch: torch.Tensor, grid: torch.Tensor, mode: str, padding_mode: str) -> torch.Tensor:
    out = F.grid_sample(batch, grid.view(1, 1, -1, 2), mode=mode, padding_mode=padding_mode, align_corners=False)
    return out[0, :, 0].transpose(0, 1)


class _WrapPad(torch.autograd.Function):
    """Circular padding of an image (C, h, w) by `pad` texels -> (1, C, h + 2 pad, w + 2 pad): F.pad's
    circular mode, with a backward that copies the gradient's interior once and adds the borders back onto it
    (autograd's backward of F.pad clears and accumulates whole images several times: a tenth of a phase-2 step
    at 2K, measured)."""

    @staticmethod
    def forward(ctx, image: torch.Tensor, pad: int) -> torch.Tensor:
        ctx.pad = pad
        return F.pad(image.unsqueeze(0), (pad, pad, pad, pad), mode="circular")

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        p = ctx.pad
        g = grad[0]
        rows = g[:, p:-p].clone()  # (C, h, w + 2p): fold the top and bottom borders onto the rows they copy
        rows[:, -p:] += g[:, :p]
        rows[:, :p] += g[:, -p:]
        image = rows[:, :, p:-p].clone()  # then the left and right borders onto the columns
        image[:, :, -p:] += rows[:, :, :p]
        image[:, :, :p] += rows[:, :, -p:]
        return image, None


def wrap_pad(image: torch.Tensor, pad: int) -> torch.Tensor:
    """(C, h, w) -> (1, C, h + 2 pad, w + 2 pad), repeated circularly (pad <= h, w)."""
    return _WrapPad.apply(image, pad)


def _addressed(image: torch.Tensor, address: Address, pad: int) -> torch.Tensor:
    """(C, h, w) -> the (1, C, ., .) image grid_sample reads for `address`: circularly padded by `pad` texels
    for wrap (grid_sample has no repeat mode; the filter's taps never reach past the pad), as it is for clamp."""
    return wrap_pad(image, pad) if address == "wrap" else image.unsqueeze(0)


def _sample_addressed(addressed: torch.Tensor, uv: torch.Tensor, width: int, height: int, address: Address,
                      mode: str, pad: int) -> torch.Tensor:
    """grid_sample an `_addressed` image of a width x height level at uv (N, 2) -> (N, C)."""
    if address == "wrap":
        return _grid_sample(addressed, _wrap_grid(uv, width, height, pad), mode, "zeros")  # zeros: unreachable
    return _grid_sample(addressed, uv * 2.0 - 1.0, mode, "border")


def _sample(image: torch.Tensor, uv: torch.Tensor, address: Address, mode: str, pad: int) -> torch.Tensor:
    """grid_sample an image (C, h, w) at uv (N, 2) -> (N, C) with `address`ing."""
    _, h, w = image.shape
    return _sample_addressed(_addressed(image, address, pad), uv, w, h, address, mode, pad)


def sample_bilinear(image: torch.Tensor, uv: torch.Tensor, address: Address) -> torch.Tensor:
    """Bilinear lookup, what a texture unit does within one mip level: image (C, h, w), uv (N, 2) -> (N, C)."""
    return _sample(image, uv, address, "bilinear", 1)


def sample_bicubic(image: torch.Tensor, uv: torch.Tensor, address: Address) -> torch.Tensor:
    """Bicubic lookup (Keys' cubic convolution, a = -0.75, as torch implements it): (C, h, w), (N, 2) -> (N, C).
    Used for the reference material only."""
    return _sample(image, uv, address, "bicubic", _BICUBIC_PAD)


def trilinear_levels(s: float, levels: int) -> tuple[int, int, float]:
    """Paper eq. 10 for a pyramid of `levels` mips sampled at level s: the two levels and the weight of the
    second. s is clamped to [0, levels - 1] as a texture unit clamps the LOD; below 0 is magnification of
    level 0 (bilinear), so the finest level is used alone."""
    s = min(max(s, 0.0), float(levels - 1))
    low = int(math.floor(s))
    high = min(low + 1, levels - 1)
    return low, high, s - low


def material_mip_count(width: int, height: int) -> int:
    """Number of mips of the material pyramid: down to the level whose shorter side is 4 texels
    (the same floor as the feature pyramids: a BC6H block)."""
    return int(math.log2(min(width, height))) - 1


def texel_centres(width: int, height: int, rows: slice | None = None, device: str | torch.device = "cpu",
                  jitter: torch.Generator | None = None) -> torch.Tensor:
    """uv (N, 2) of the texel centres of a width x height image, row-major, for the given rows (all by
    default). With `jitter`, each point moves to a uniformly random position inside its texel (the 1 sample
    per pixel evaluation of paper §6.2)."""
    rows = rows or slice(0, height)
    y = torch.arange(rows.start, min(rows.stop, height), dtype=torch.float32, device=device)
    x = torch.arange(width, dtype=torch.float32, device=device)
    gy, gx = torch.meshgrid(y, x, indexing="ij")
    points = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=1)
    if jitter is None:
        points = points + 0.5
    else:
        points = points + torch.rand(points.shape, generator=jitter, dtype=torch.float32).to(device)
    return points / torch.tensor([width, height], dtype=torch.float32, device=device)


class ReferenceMaterial:
    """The filtered reference F(M)(u, v, s) of paper §5.1: bicubic lookups in the two mips around s,
    blended linearly.

    The pyramid is built by `images.mip_chain` (2x2 box filter) on the stored 8-channel values, normal x and
    y included: averaging the stored normal components is what a texture unit does to a BC5 normal map, and
    z is rebuilt from the filtered x, y after decoding. Levels go down to a shorter side of 4 texels.
    """

    def __init__(self, channels: np.ndarray, address: Address, device: str | torch.device = "cpu"):
        """channels: (H, W, C) float32 material (C = 8 for bcf's albedo, normal xy, ARM)."""
        height, width = channels.shape[:2]
        self.width, self.height = width, height
        self.address = address
        self.mips = [torch.from_numpy(np.ascontiguousarray(m.transpose(2, 0, 1))).to(device)
                     for m in images.mip_chain(channels, material_mip_count(width, height))]
        # The lookup copies: wrap padding done once (padding a 2K, 8-channel mip per lookup was a third of a
        # training step), channels last so that a bicubic tap reads a texel's 8 channels from one cache line,
        # not 8 planes (the same values; 3.9x faster lookups of random points in the 2K mip, docs/BENCHMARKS.md).
        self._lookup = [_addressed(m, address, _BICUBIC_PAD).contiguous(memory_format=torch.channels_last)
                        for m in self.mips]

    @property
    def levels(self) -> int:
        return len(self.mips)

    def sample(self, uv: torch.Tensor, s: float) -> torch.Tensor:
        """F(M)(u, v, s): uv (N, 2), s in [0, levels - 1] -> (N, C)."""
        low, high, weight = trilinear_levels(s, self.levels)
        value = self._bicubic(low, uv)
        if weight > 0.0:
            value = torch.lerp(value, self._bicubic(high, uv), weight)
        return value

    def _bicubic(self, level: int, uv: torch.Tensor) -> torch.Tensor:
        """`sample_bicubic` of mip `level`, through its lookup copy."""
        _, h, w = self.mips[level].shape
        return _sample_addressed(self._lookup[level], uv, w, h, self.address, "bicubic", _BICUBIC_PAD)

    def mip(self, level: int) -> torch.Tensor:
        """The stored mip `level` as (C, h, w)."""
        return self.mips[level]


def sample_trilinear(level: Callable[[int], torch.Tensor], levels: int, uv: torch.Tensor, s: float,
                     address: Address) -> torch.Tensor:
    """Trilinear lookup (paper eq. 10) in a pyramid of `levels` mips: (N, 2) -> (N, C). `level(l)` returns
    mip l as (C, h, w); only the one or two mips that s needs are requested (block features decode them)."""
    low, high, weight = trilinear_levels(s, levels)
    value = sample_bilinear(level(low), uv, address)
    if weight > 0.0:
        value = torch.lerp(value, sample_bilinear(level(high), uv, address), weight)
    return value
