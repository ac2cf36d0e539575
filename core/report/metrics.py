"""Quality metrics: PSNR and SSIM on stored values in [0, 1], per texture and per mip, and the evaluation
of a decoder (trained or read back from files) against the reference material's mip pyramid.

Aggregation follows the paper (§6.1, after Vaidyanathan et al.): PSNR of the mean MSE over mips; SSIM is
the mean over mips.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from bcf.core.export.decode import DecoderFunction, render_mip
from bcf.core.fit.sampling import ReferenceMaterial
from bcf.core.material.roles import TEXTURES
from bcf.core.psnr import psnr_from_mse

__all__ = ["GROUPS", "MipScores", "evaluate", "mean_baseline", "ssim"]

# Score groups: the three textures and all 8 channels together.
GROUPS: dict[str, slice] = {**TEXTURES, "all": slice(0, 8)}
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03

MipScores = dict[str, dict[str, float]]  # {"mse" | "psnr" | "ssim": {group: value}}


def _gaussian_window(size: int, sigma: float, device: torch.device) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64, device=device) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(torch.float32)


def ssim(reference: torch.Tensor, test: torch.Tensor) -> float:
    """Mean SSIM (Wang et al. 2004; Gaussian window 11, sigma 1.5, K1 0.01, K2 0.03, data range 1) over
    the valid window positions and the channels of (C, h, w) images. Images smaller than 11 texels use
    the largest odd window that fits, with sigma scaled alike, so every mip gets a score."""
    size = min(SSIM_WINDOW, reference.shape[1], reference.shape[2])
    size -= 1 - size % 2
    g = _gaussian_window(size, SSIM_SIGMA * size / SSIM_WINDOW, reference.device)
    channels = reference.shape[0]

    def blur(x: torch.Tensor) -> torch.Tensor:  # separable, 'valid' positions only
        x = F.conv2d(x.unsqueeze(0), g.view(1, 1, 1, -1).expand(channels, 1, 1, size), groups=channels)
        return F.conv2d(x, g.view(1, 1, -1, 1).expand(channels, 1, size, 1), groups=channels)[0]

    x, y = reference.to(torch.float32), test.to(torch.float32)
    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    value = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return float(value.mean())


def _scores(reference: torch.Tensor, test: torch.Tensor) -> MipScores:
    out: MipScores = {"mse": {}, "psnr": {}, "ssim": {}}
    for name, channels in GROUPS.items():
        r, t = reference[channels], test[channels]
        mse = float(torch.mean((r - t) ** 2))
        out["mse"][name] = mse
        out["psnr"][name] = psnr_from_mse(mse)
        out["ssim"][name] = ssim(r, t)
    return out


@torch.no_grad()
def evaluate(decoder: DecoderFunction, reference: ReferenceMaterial,
             jitter_seed: Optional[int] = None) -> list[MipScores]:
    """Scores of `decoder` at every mip m of the reference (scale s = m).

    Without jitter: the decoder at the texel centres of mip m against the stored mip. With `jitter_seed`: the
    1 sample per pixel evaluation of §6.2: one uniformly random point inside every texel, compared with the
    filtered reference F(M) at the same point and scale."""
    generator = None if jitter_seed is None else torch.Generator().manual_seed(jitter_seed)
    results = []
    for level in range(reference.levels):
        target = reference.mip(level)
        _, h, w = target.shape
        if generator is None:
            test = render_mip(decoder, w, h, float(level))
        else:
            state = generator.get_state()
            test = render_mip(decoder, w, h, float(level), generator)
            generator.set_state(state)  # the same points for the reference
            target = render_mip(reference.sample, w, h, float(level), generator).clamp(0.0, 1.0)
        # Scores are on stored values in [0, 1]: a renderer saturates the decoder's output, and so does
        # `bcf decode`, so the report matches the decoded files.
        results.append(_scores(target, test.to(target.device).clamp(0.0, 1.0)))
    return results


def mean_baseline(reference: ReferenceMaterial) -> list[MipScores]:
    """Scores of the trivial predictor that outputs the material's per-channel mean everywhere: any
    useful decoder must beat it by a wide margin."""
    mean = reference.mip(0).mean(dim=(1, 2), keepdim=True)
    return [_scores(m, mean.expand_as(m)) for m in (reference.mip(l) for l in range(reference.levels))]
