"""A start for the fit from the material itself: its principal components (seed paper
neural-material-decompression-svd; docs/BENCHMARKS.md, issue 15).

The material's channels are projected on their principal axes (a PCA of mip 0). The coefficients of the
strongest components go into the free features, one component per feature channel in order (T0 holds
components 0-2, T1 3-5, T2 6-7 for an 8-channel material), each mip of each pyramid the coefficients of the
material mip of its size (a box filter of the coefficients: projection and box filter commute). The decoder
starts as the inverse projection: one hidden unit per component, biased so that its ReLU never clips, and
output weights equal to the principal axes; its other hidden units start with zero output weights.

So before any training step the model reproduces every material mip at least as coarse as the pyramid
holding each component, exactly (up to float rounding), and the finest mip up to the components' resolutions.
"""

from __future__ import annotations

from functools import lru_cache, partial
from typing import Sequence

import torch
import torch.nn.functional as F

from bcf.core.fit.model import FEATURE_CHANNELS, Decoder, FeatureTextureSpec, FreeFeatures
from bcf.core.fit.sampling import ReferenceMaterial

__all__ = ["PrincipalComponents", "pca_start", "principal_components"]

# Coefficients are stored as 0.5 + coefficient * SPREAD / (standard deviation of the first component): the
# first component's +-4 sigma span [0, 1] and every other component keeps its scale relative to the first, so
# the features of one texture are commensurate (the transition then maps them with one range per texture).
SPREAD = 0.125
UNUSED_NOISE = 0.05  # feature channels without a component: 0.5 plus uniform noise of this half-width
_CHUNK = 1 << 20  # texels per step of the covariance sum (bounded memory at any material size)


class PrincipalComponents:
    """mean (C,), axes (C, C) (column k is component k, strongest first) and standard deviations (C,) of the
    texels of one image, float64."""

    def __init__(self, mean: torch.Tensor, axes: torch.Tensor, sigma: torch.Tensor):
        self.mean, self.axes, self.sigma = mean, axes, sigma

    def _chunks(self, image: torch.Tensor):
        """(start, coefficients (C, n) float32) of `image`'s texels, a chunk at a time (bounded memory)."""
        flat = image.reshape(image.shape[0], -1)
        axes, mean = self.axes.T.float(), self.mean.float()[:, None]
        for start in range(0, flat.shape[1], _CHUNK):
            yield start, axes @ (flat[:, start:start + _CHUNK].float() - mean)

    def coefficients(self, image: torch.Tensor) -> torch.Tensor:
        """(C, h, w) image -> (C, h, w) float32 coefficients on the axes."""
        out = torch.empty(image.shape, dtype=torch.float32, device=image.device).reshape(image.shape[0], -1)
        for start, chunk in self._chunks(image):
            out[:, start:start + chunk.shape[1]] = chunk
        return out.reshape(image.shape)

    def lowest(self, image: torch.Tensor) -> torch.Tensor:
        """(C,) smallest coefficient of each component over `image`'s texels."""
        return torch.stack([chunk.amin(dim=1) for _, chunk in self._chunks(image)]).amin(dim=0)


def principal_components(image: torch.Tensor) -> PrincipalComponents:
    """PCA of the texels of a (C, h, w) image (covariance summed in float64, a chunk of texels at a time)."""
    flat = image.reshape(image.shape[0], -1)
    count = flat.shape[1]
    total = torch.zeros(flat.shape[0], dtype=torch.float64, device=image.device)
    products = torch.zeros(flat.shape[0], flat.shape[0], dtype=torch.float64, device=image.device)
    for start in range(0, count, _CHUNK):
        chunk = flat[:, start:start + _CHUNK].double()
        total += chunk.sum(1)
        products += chunk @ chunk.T
    mean = total / count
    covariance = products / count - torch.outer(mean, mean)
    variance, axes = torch.linalg.eigh(covariance)  # ascending
    order = torch.argsort(variance, descending=True)
    return PrincipalComponents(mean, axes[:, order], variance[order].clamp(min=0.0).sqrt())


def _level_coefficients(pca: PrincipalComponents, reference: ReferenceMaterial, width: int,
                        height: int) -> torch.Tensor:
    """Coefficients (C, height, width) of the material mip of that size; where the material has none (tiny
    materials, whose feature levels are padded to whole blocks), mip 0's coefficients area-resampled."""
    for mip in reference.mips:
        if tuple(mip.shape[1:]) == (height, width):
            return pca.coefficients(mip)
    return F.adaptive_avg_pool2d(pca.coefficients(reference.mip(0))[None], (height, width))[0]


def pca_start(reference: ReferenceMaterial, specs: Sequence[FeatureTextureSpec], hidden: int,
              generator: torch.Generator) -> tuple[FreeFeatures, Decoder]:
    """Free features and a decoder that together are the material's principal-component reconstruction
    (module docstring). `generator` draws the noise of unused feature channels; the decoder's other hidden
    units keep torch's default initialisation of their input weights (the global generator, seeded by
    `fit`)."""
    pca = principal_components(reference.mip(0))
    device = reference.mip(0).device
    channels = len(pca.sigma)
    slots = len(specs) * FEATURE_CHANNELS
    components = min(channels, slots, hidden)
    gain = SPREAD / max(float(pca.sigma[0]), 1e-6)
    free = FreeFeatures(specs, generator)
    # Several pyramids have levels of one size (T0's level 1 is T1's level 0): each size projected once.
    coefficients_of = lru_cache(maxsize=None)(partial(_level_coefficients, pca, reference))
    with torch.no_grad():
        for texture, spec in enumerate(specs):
            for level in range(spec.levels):
                texels = free.level(texture, level)
                texels.copy_(0.5 + UNUSED_NOISE * (2.0 * texels - 1.0))  # the constructor's uniform draw, rescaled
                first = texture * FEATURE_CHANNELS
                used = range(first, min(first + FEATURE_CHANNELS, components))
                if len(used):
                    width, height = spec.level_size(level)
                    coefficients = coefficients_of(width, height)
                    texels[: len(used)] = 0.5 + coefficients[used.start:used.stop].to(texels.device) * gain
    free = free.to(device)
    decoder = Decoder(hidden).to(device)
    lowest = pca.lowest(reference.mip(0)).double()  # box filters never go below these
    with torch.no_grad():
        # Unit k computes coefficient k plus a bias that keeps it positive, so its ReLU passes it unchanged:
        # h_k = (x_k - 0.5) / gain + bias_k; the output layer adds axis_k * (h_k - bias_k) to the mean.
        bias = (-lowest[:components]).clamp(min=0.0) + 0.01 * pca.sigma[0]
        decoder.hidden.weight[:components] = 0.0
        decoder.hidden.weight[range(components), range(components)] = 1.0 / gain
        decoder.hidden.bias[:components] = (bias - 0.5 / gain).float()
        decoder.output.weight.zero_()
        decoder.output.weight[:, :components] = pca.axes[:, :components].float()
        decoder.output.bias.copy_((pca.mean - pca.axes[:, :components] @ bias).float())
    return free, decoder
