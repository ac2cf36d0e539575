"""The neural material of the paper (§3-5): four feature pyramids T0..T3 of 3 channels, sampled trilinearly
at (u, v, s), concatenated and decoded by a small MLP into the 8 material channels (eq. 3).

Feature pyramids come in three kinds that share one sampling path (`NeuralMaterial`):
- `FreeFeatures`: unconstrained float parameters per texel (phase 1).
- `BlockFeatures`: per 4x4 block BC6H endpoints, weights and a fixed partition, decoded with the exact
  BC6H pipeline in the forward pass (phase 2, §4.1-4.2); exported bit for bit.
- `StaticFeatures`: decoded texel values read back from exported files (the reference decoder).

The MLP reads each sampled feature value times a learnable per-channel scale plus offset
(`Decoder.input_scale/input_offset`); export folds scale and offset into the first layer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np
import torch
from torch import nn

from bcf.core.codec import bc6h, partition
from bcf.core.fit import block_decode
from bcf.core.fit.sampling import sample_trilinear
from bcf.core.options import FEATURE_SCALES, Address

__all__ = ["FEATURE_CHANNELS", "FEATURE_TEXTURES", "OUTPUT_CHANNELS", "BlockFeatures", "Decoder",
           "FeatureTextureSpec", "FreeFeatures", "NeuralMaterial", "StaticFeatures", "feature_textures",
           "to_block_features"]

FEATURE_TEXTURES = 4
FEATURE_CHANNELS = 3
OUTPUT_CHANNELS = 8

# The transition to block features maps each feature channel's 0.05 %-99.95 % quantile range onto the half
# values [0, 1]. (Any range works alike for the log-spaced UF16 endpoints; [0, 1] keeps values readable.)
QUANTILES = (0.0005, 0.9995)
STORED_RANGE = (0.0, 1.0)


@dataclass(frozen=True)
class FeatureTextureSpec:
    """One feature pyramid: level 0 size, number of mips (down to a shorter side of 4 texels, one BC6H
    block) and the LOD bias b_i of eq. 11, log2 of its size relative to the material's."""

    width: int
    height: int
    levels: int
    lod_bias: float

    def level_size(self, level: int) -> tuple[int, int]:
        return self.width >> level, self.height >> level


def feature_textures(material_width: int, material_height: int, features: str) -> tuple[FeatureTextureSpec, ...]:
    """T0 at material size x {0.25, 0.5, 1} (`features` 0.5k / 1k / 2k), T_i = T0 / 2^i, each side at
    least 4 (so tiny materials still get whole blocks)."""
    scale = FEATURE_SCALES[features]
    specs = []
    for i in range(FEATURE_TEXTURES):
        w = max(4, int(material_width * scale) >> i)
        h = max(4, int(material_height * scale) >> i)
        levels = int(math.log2(min(w, h))) - 1
        bias = math.log2(max(w / material_width, h / material_height))
        specs.append(FeatureTextureSpec(w, h, levels, bias))
    return tuple(specs)


# ------------------------------------------------------------------------------------------------ the MLP


class Decoder(nn.Module):
    """f_eta of eq. 3: input scale/offset, Linear(12, hidden), ReLU, Linear(hidden, 8), identity output.
    (ReLU after the hidden layer only: the paper's 'ReLU for the input and hidden layers' read literally
    would clip the features.)"""

    def __init__(self, hidden: int, inputs: int = FEATURE_TEXTURES * FEATURE_CHANNELS,
                 outputs: int = OUTPUT_CHANNELS):
        super().__init__()
        self.hidden = nn.Linear(inputs, hidden)
        self.output = nn.Linear(hidden, outputs)
        self.input_scale = nn.Parameter(torch.ones(inputs))
        self.input_offset = nn.Parameter(torch.zeros(inputs))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (N, 12) encoded features -> (N, 8) material channels."""
        return self.output(torch.relu(self.hidden(x * self.input_scale + self.input_offset)))

    def folded_layers(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """[(W1, b1), (W2, b2)] (W is (out, in)) with the input scale and offset folded into layer 1:
        W1 (x * scale + offset) + b1 = (W1 * scale) x + (b1 + W1 offset)."""
        with torch.no_grad():
            w1 = self.hidden.weight * self.input_scale[None, :]
            b1 = self.hidden.bias + self.hidden.weight @ self.input_offset
            return [(w1.clone(), b1.clone()), (self.output.weight.clone(), self.output.bias.clone())]

    @classmethod
    def from_layers(cls, layers: Sequence[tuple[torch.Tensor, torch.Tensor]]) -> "Decoder":
        """A decoder with the given (W, b) layers and identity input scale/offset."""
        (w1, b1), (w2, b2) = layers
        decoder = cls(w1.shape[0], w1.shape[1], w2.shape[0])
        with torch.no_grad():
            decoder.hidden.weight.copy_(w1)
            decoder.hidden.bias.copy_(b1)
            decoder.output.weight.copy_(w2)
            decoder.output.bias.copy_(b2)
        return decoder


# ------------------------------------------------------------------------------------------ feature kinds


class FreeFeatures(nn.Module):
    """Unconstrained features (phase 1): one (3, h, w) parameter per texture and mip, every mip independent
    (§4.3), initialised uniformly in [0, 1)."""

    def __init__(self, specs: Sequence[FeatureTextureSpec], generator: torch.Generator):
        super().__init__()
        self.specs = tuple(specs)
        self.texels = nn.ParameterList()
        for spec in self.specs:
            for level in range(spec.levels):
                w, h = spec.level_size(level)
                self.texels.append(nn.Parameter(torch.rand(FEATURE_CHANNELS, h, w, generator=generator)))
        self._start = np.cumsum([0] + [s.levels for s in self.specs])

    def level(self, texture: int, level: int) -> torch.Tensor:
        return self.texels[int(self._start[texture]) + level]


class StaticFeatures(nn.Module):
    """Fixed, already decoded feature levels: levels[texture][mip] is a (3, h, w) tensor."""

    def __init__(self, specs: Sequence[FeatureTextureSpec], levels: Sequence[Sequence[torch.Tensor]]):
        super().__init__()
        self.specs = tuple(specs)
        for texture, pyramid in enumerate(levels):
            for level, image in enumerate(pyramid):
                self.register_buffer(f"level_{texture}_{level}", image)

    def level(self, texture: int, level: int) -> torch.Tensor:
        return getattr(self, f"level_{texture}_{level}")


class BlockFeatures(nn.Module):
    """Block-based features (§4.1): per 4x4 block of every texture mip, R segments of 2 endpoints (3
    channels), 16 weights and a fixed partition, stored normalised: endpoints / (2^bits - 1) and weights in
    [0, 1], so learning rates mean the same for mode 10 and 11. Blocks are row-major over the level.

    `level()` decodes with `block_decode` (`decode_level_one_region` in mode 11): bit-exact forward (the exported
    texture), straight-through rounding and the eq. 7-9 surrogate backward."""

    def __init__(self, specs: Sequence[FeatureTextureSpec], mode: Literal[10, 11],
                 fits: Sequence[partition.BlockFit], device: str | torch.device = "cpu"):
        super().__init__()
        self.specs = tuple(specs)
        self.mode = mode
        self.spec = bc6h.mode_spec(mode)
        self.top = float((1 << self.spec.endpoint_bits) - 1)
        self.endpoints = nn.ParameterList()
        self.weights = nn.ParameterList()
        for number, fit in enumerate(fits):
            self.endpoints.append(nn.Parameter(torch.tensor(fit.endpoints / self.top, dtype=torch.float32,
                                                            device=device)))
            self.weights.append(nn.Parameter(torch.tensor(fit.weights, dtype=torch.float32, device=device)))
            # Buffers, so that .to(device) moves them with the parameters.
            self.register_buffer(f"partition_{number}", torch.as_tensor(fit.partition, device=device))
        self._start = np.cumsum([0] + [s.levels for s in self.specs])

    def _partition(self, index: int) -> torch.Tensor:
        return getattr(self, f"partition_{index}")

    def _index(self, texture: int, level: int) -> int:
        return int(self._start[texture]) + level

    def level(self, texture: int, level: int) -> torch.Tensor:
        i = self._index(texture, level)
        w, h = self.specs[texture].level_size(level)
        if self.spec.regions == 1:  # the default presets' mode: closed-form decode straight into image layout
            return block_decode.decode_level_one_region(self.endpoints[i] * self.top, self.weights[i], h // 4,
                                                        w // 4)
        partition = self._partition(i)
        texels = block_decode.decode_blocks_differentiable(self.endpoints[i] * self.top, self.weights[i],
                                                           partition, signed=False)  # (nb, 16, 3)
        return texels.view(h // 4, w // 4, 4, 4, 3).permute(4, 0, 2, 1, 3).reshape(3, h, w)

    def clamp_(self) -> None:
        """Keep parameters in their stored ranges (rounding clamps anyway; this stops them drifting far
        outside where the straight-through gradient would no longer bring them back)."""
        with torch.no_grad():
            for p in list(self.endpoints) + list(self.weights):
                p.clamp_(0.0, 1.0)

    def blocks(self, texture: int, level: int) -> np.ndarray:
        """The BC6H blocks (bh, bw, 16) uint8 of one level: the rounded parameters encoded as they are."""
        i = self._index(texture, level)
        w, h = self.specs[texture].level_size(level)
        with torch.no_grad():
            ends = block_decode.quantize_endpoints(self.endpoints[i] * self.top, self.spec.endpoint_bits, False)
            index = block_decode.quantize_weights(self.weights[i], self.spec.index_bits)
        ends_np = ends.cpu().numpy().astype(np.int64)
        index_np = index.cpu().numpy().astype(np.int64)
        if self.spec.regions == 2:
            blocks = bc6h.encode_mode10(ends_np, index_np, self._partition(i).cpu().numpy(), signed=False)
        else:
            blocks = bc6h.encode_mode11(ends_np[:, 0], index_np, signed=False)
        return blocks.reshape(h // 4, w // 4, bc6h.BLOCK_BYTES)


Features = FreeFeatures | BlockFeatures | StaticFeatures


# --------------------------------------------------------------------------------------------- the model


class NeuralMaterial(nn.Module):
    """G(u, v, s) of eq. 3: trilinear lookups (eq. 10) of the four pyramids, each at level s + b_i (eq. 11),
    concatenated in texture order T0.rgb .. T3.rgb and decoded by the MLP."""

    def __init__(self, features: Features, decoder: Decoder, address: Address):
        super().__init__()
        self.features = features
        self.decoder = decoder
        self.address = address

    def sample_features(self, uv: torch.Tensor, s: float) -> torch.Tensor:
        """The raw (decoded, filtered) feature values (N, 12) at material scale s."""
        columns = []
        for i, spec in enumerate(self.features.specs):
            columns.append(sample_trilinear(lambda level, i=i: self.features.level(i, level), spec.levels,
                                            uv, s + spec.lod_bias, self.address))
        return torch.cat(columns, dim=1)

    def forward(self, uv: torch.Tensor, s: float) -> torch.Tensor:
        """uv (N, 2), material scale s -> (N, 8) material channels."""
        return self.decoder(self.sample_features(uv, s))


# ------------------------------------------------------------------------------------ phase 1 -> phase 2


def _feature_range(free: FreeFeatures, texture: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel QUANTILES of all mips of one free feature pyramid: (3,) low and high."""
    values = torch.cat([free.level(texture, l).detach().reshape(FEATURE_CHANNELS, -1)
                        for l in range(free.specs[texture].levels)], dim=1).cpu().numpy()
    if values.shape[1] > 1 << 20:  # quantiles of a strided subsample: plenty, and far cheaper
        values = values[:, :: values.shape[1] // (1 << 20) + 1]
    low, high = np.quantile(values, QUANTILES, axis=1)
    return low, np.maximum(high, low + 1e-6)


def to_block_features(free: FreeFeatures, decoder: Decoder, mode: Literal[10, 11]) -> BlockFeatures:
    """Phase 1 -> phase 2 (§5.1): map each feature channel's value range onto STORED_RANGE, fold the inverse map
    into the decoder's input scale/offset (so the MLP sees the same inputs), then initialise the blocks by the
    partition search (`partition.fit_blocks`) on the mapped values. Changes `decoder` in place."""
    device = decoder.input_scale.device
    c0, c1 = STORED_RANGE
    fits = []
    scale = decoder.input_scale.detach().cpu().numpy().astype(np.float64)
    offset = decoder.input_offset.detach().cpu().numpy().astype(np.float64)
    regions = bc6h.mode_spec(mode).regions
    for i, spec in enumerate(free.specs):
        low, high = _feature_range(free, i)
        # The MLP read x (times scale plus offset); it will read c = c0 + (x - low) / (high - low) * (c1 - c0).
        step = (high - low) / (c1 - c0)
        channels = slice(FEATURE_CHANNELS * i, FEATURE_CHANNELS * (i + 1))
        offset[channels] = offset[channels] + scale[channels] * (low - c0 * step)
        scale[channels] = scale[channels] * step
        for level in range(spec.levels):
            x = free.level(i, level).detach().cpu().numpy().astype(np.float64).transpose(1, 2, 0)
            stored = np.clip(c0 + (x - low) / (high - low) * (c1 - c0), c0, c1)
            fits.append(partition.fit_blocks(bc6h.image_to_block_texels(stored).reshape(-1, 16, 3), regions,
                                             signed=False))
    with torch.no_grad():
        decoder.input_scale.copy_(torch.from_numpy(scale))
        decoder.input_offset.copy_(torch.from_numpy(offset))
    return BlockFeatures(free.specs, mode, fits, device)
