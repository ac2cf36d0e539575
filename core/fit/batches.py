"""Training batches: where the fit samples the material at each step (paper §5.1; RTXNTC's texel sampling).

Every step takes one scale s (the feature mips it needs are decoded once per step) and a set of points, and the
target is the reference material there. Steps come in three kinds:

- continuous (the paper's): uv uniform in [0, 1)², s uniform in [0, S - 1]; the target is F(M)(u, v, s), bicubic
  lookups in the two mips around s, and the features are blended between two mips (eq. 10).
- mip steps: one integer mip l, every mip equally likely, so each pyramid needs one feature mip and the reference
  one bicubic lookup. Their points are either
  - texel centres of mip l: the target is a lookup in the stored mip, not a resampling, and the step is scored
    where the report scores; or
  - jittered: uniformly inside the texels of mip l, where the report's 1 spp score and engines sample too.
  A mip with no more texels than the batch is taken whole, every texel once (a dense step).

Mips are drawn alike, not by area as RTXNTC does: the report weighs every mip alike (mean MSE over mips), and
each feature mip is its own parameters, trained only when its scale is drawn. By area, the coarse mips were
starved: 2.0 dB below mips drawn alike (1.3 below the paper's sampling) after a 1,000 + 2,000-iteration fit at
2K (docs/BENCHMARKS.md). Texel centres alone raise
the report's PSNR at centres but not between them (the 1 spp score): the presets mix the kinds as measured there.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from bcf.core.fit.sampling import ReferenceMaterial

__all__ = ["Batch", "BatchSampler"]


@dataclass(frozen=True)
class Batch:
    uv: torch.Tensor  # (N, 2)
    s: float  # material scale of every point
    target: torch.Tensor  # (N, C) reference values


class BatchSampler:
    """Draws the batches of one fit. Randomness: the step kind, the mip and s come from `step_generator`
    (on the host: they pick which mips to decode), the points from `generator` (on the training device). With
    continuous_fraction 1 the draws are exactly those of a continuous-only fit.

    continuous_fraction: the fraction of continuous steps; centre_fraction: the fraction of mip steps at texel
    centres (the others are jittered)."""

    def __init__(self, reference: ReferenceMaterial, batch_size: int, continuous_fraction: float,
                 centre_fraction: float, generator: torch.Generator, step_generator: torch.Generator):
        self.reference = reference
        self.batch_size = batch_size
        self.continuous_fraction = continuous_fraction
        self.centre_fraction = centre_fraction
        self.generator = generator
        self.step_generator = step_generator
        self._sizes = [(m.shape[2], m.shape[1]) for m in reference.mips]
        self._device = reference.mips[0].device
        self._texels: dict[int, torch.Tensor] = {}  # mip -> (h * w, C), rows are texels: gathers read 32 bytes

    def __call__(self) -> Batch:
        if self._chance(self.continuous_fraction):
            return self._continuous()
        return self._mip_step(centres=self._chance(self.centre_fraction))

    def _chance(self, fraction: float) -> bool:
        """True with probability `fraction`; draws nothing when the answer is certain."""
        return fraction >= 1.0 or (fraction > 0.0 and float(torch.rand((), generator=self.step_generator)) < fraction)

    def _continuous(self) -> Batch:
        s = float(torch.rand((), generator=self.step_generator)) * (self.reference.levels - 1)
        uv = torch.rand((self.batch_size, 2), generator=self.generator, device=self._device)
        with torch.no_grad():
            return Batch(uv, s, self.reference.sample(uv, s))

    def _mip_step(self, centres: bool) -> Batch:
        mip = int(torch.randint(0, len(self._sizes), (), generator=self.step_generator))
        w, h = self._sizes[mip]
        device = self._device
        if w * h <= self.batch_size:
            index = torch.arange(w * h, device=device)  # dense: every texel once
        else:
            index = torch.randint(0, w * h, (self.batch_size,), generator=self.generator, device=device)
        texel = torch.stack([index % w, torch.div(index, w, rounding_mode="floor")], dim=1).to(torch.float32)
        size = torch.tensor([w, h], dtype=torch.float32, device=device)
        if centres:
            return Batch((texel + 0.5) / size, float(mip), self._mip_texels(mip).index_select(0, index))
        uv = (texel + torch.rand(texel.shape, generator=self.generator, device=device)) / size
        with torch.no_grad():
            return Batch(uv, float(mip), self.reference.sample(uv, float(mip)))

    def _mip_texels(self, mip: int) -> torch.Tensor:
        if mip not in self._texels:
            image = self.reference.mip(mip)
            self._texels[mip] = image.reshape(image.shape[0], -1).t().contiguous()
        return self._texels[mip]
