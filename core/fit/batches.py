"""Training batches: where the fit samples the material at each step (paper §5.1; RTXNTC's texel sampling).

Every step takes one scale s (the feature mips it needs are decoded once per step) and a set of points, and the
target is the reference material there. Two kinds of step:

- continuous (the paper's): uv uniform in [0, 1)², s uniform in [0, S - 1]; the target is F(M)(u, v, s), bicubic
  lookups in the two mips around s.
- texel: one integer mip l, drawn with probability proportional to texels(l)^mip_power; the points are texel
  centres of mip l, so the target is a lookup in the stored mip, not a resampling, and the step is scored where
  the report scores. A mip with no more texels than the batch is taken whole, every texel once (a dense step).

A fraction of continuous steps keeps what texel steps never see learned: positions between texel centres and
scales between mips, where engines sample too (the 1-spp jittered score of the report measures it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bcf.core.fit.sampling import ReferenceMaterial

__all__ = ["Batch", "BatchSampler", "mip_probabilities"]


@dataclass(frozen=True)
class Batch:
    uv: torch.Tensor  # (N, 2)
    s: float  # material scale of every point
    target: torch.Tensor  # (N, C) reference values


def mip_probabilities(texels: list[int], power: float) -> np.ndarray:
    """Probability of each mip for a texel step: texels^power, normalised (1: by area, as RTXNTC; 0: uniform)."""
    weights = np.asarray(texels, dtype=np.float64) ** power
    return weights / weights.sum()


class BatchSampler:
    """Draws the batches of one fit. Randomness: the step kind, the mip and s come from `step_generator`
    (on the host: they pick which mips to decode), the points from `generator` (on the training device). With
    continuous_fraction 1 the draws are exactly those of a continuous-only fit."""

    def __init__(self, reference: ReferenceMaterial, batch_size: int, continuous_fraction: float,
                 mip_power: float, generator: torch.Generator, step_generator: torch.Generator):
        self.reference = reference
        self.batch_size = batch_size
        self.continuous_fraction = continuous_fraction
        self.generator = generator
        self.step_generator = step_generator
        sizes = [(m.shape[2], m.shape[1]) for m in reference.mips]
        self._sizes = sizes
        self._cumulative = torch.from_numpy(np.cumsum(mip_probabilities([w * h for w, h in sizes], mip_power)))
        self._texels: dict[int, torch.Tensor] = {}  # mip -> (h * w, C), rows are texels: gathers read 32 bytes

    def __call__(self) -> Batch:
        fraction = self.continuous_fraction
        if fraction >= 1.0 or (fraction > 0.0 and float(torch.rand((), generator=self.step_generator)) < fraction):
            return self._continuous()
        return self._texel_step()

    def _continuous(self) -> Batch:
        s = float(torch.rand((), generator=self.step_generator)) * (self.reference.levels - 1)
        device = self.reference.mips[0].device
        uv = torch.rand((self.batch_size, 2), generator=self.generator, device=device)
        with torch.no_grad():
            return Batch(uv, s, self.reference.sample(uv, s))

    def _texel_step(self) -> Batch:
        u = torch.rand((), generator=self.step_generator, dtype=torch.float64)
        mip = min(int(torch.searchsorted(self._cumulative, u, right=True)), len(self._sizes) - 1)
        w, h = self._sizes[mip]
        texels = self._mip_texels(mip)
        if w * h <= self.batch_size:
            index = torch.arange(w * h, device=texels.device)  # dense: every texel once
        else:
            index = torch.randint(0, w * h, (self.batch_size,), generator=self.generator, device=texels.device)
        x = (index % w).to(torch.float32)
        y = torch.div(index, w, rounding_mode="floor").to(torch.float32)
        uv = torch.stack([(x + 0.5) / w, (y + 0.5) / h], dim=1)
        return Batch(uv, float(mip), texels.index_select(0, index))

    def _mip_texels(self, mip: int) -> torch.Tensor:
        if mip not in self._texels:
            image = self.reference.mip(mip)
            self._texels[mip] = image.reshape(image.shape[0], -1).t().contiguous()
        return self._texels[mip]
