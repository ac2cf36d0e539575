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
from bcf.core.codec.textures import encoder_modes
from bcf.core.fit import block_decode
from bcf.core.fit.sampling import sample_trilinear
from bcf.core.options import FEATURE_SCALES, Address, BlockMode

__all__ = ["FEATURE_CHANNELS", "FEATURE_TEXTURES", "OUTPUT_CHANNELS", "BlockFeatures", "Decoder",
           "FeatureTextureSpec", "FreeFeatures", "NeuralMaterial", "StaticFeatures", "feature_textures",
           "to_block_features"]

FEATURE_TEXTURES = 4
FEATURE_CHANNELS = 3
OUTPUT_CHANNELS = 8

# The transition to block features maps each feature channel's 0.05 %-99.95 % quantile range onto half values:
# - [0, 1] for a fixed mode (10 or 11): it spans many octaves of the log-spaced half floats, so small values get
#   finer endpoints (any range [0, x] works alike; [0, 1] keeps values readable);
# - [0.5, 1] for a per-block mode choice: one octave, where half-float bits are linear in the value, so a block's
#   segment in BC6H's interpolation domain is a straight segment of feature values too. Its one-region modes then
#   have 33 (mode 11) to 132 (mode 13) endpoint levels across the range. Measured at the transition, PCA start:
#   +0.22 dB on Bricks075B (512), +0.19 dB on the 2K wood material, +0.01 dB on denim (docs/BENCHMARKS.md).
QUANTILES = (0.0005, 0.9995)
STORED_RANGE = {"fixed": (0.0, 1.0), "auto": (0.5, 1.0)}


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
    """Block-based features (§4.1): every 4x4 block of every texture mip is one BC6H block in a mode of its own
    (chosen at the transition: one fixed mode for all, or each block's best), held as two segments of
    continuous endpoints normalised by the mode's largest endpoint, 16 weights in [0, 1] (positions on the
    segments, normalised by the largest index) and a partition. One-region blocks use segment 0. Blocks are
    row-major over the level.

    `level()` decodes with `block_decode.decode_level`: bit-exact forward (the exported texture),
    straight-through rounding and the eq. 7-9 surrogate backward."""

    def __init__(self, specs: Sequence[FeatureTextureSpec], fits: Sequence[partition.BlockFit],
                 device: str | torch.device = "cpu"):
        super().__init__()
        self.specs = tuple(specs)
        self.endpoints = nn.ParameterList()
        self.weights = nn.ParameterList()
        self._two_regions: list[bool] = []
        for number, fit in enumerate(fits):
            modes = block_decode.BlockModes.of(torch.as_tensor(fit.mode), torch.as_tensor(fit.partition))
            top = modes.top.to(torch.float32)[:, None, None, None]
            self.endpoints.append(nn.Parameter((torch.as_tensor(fit.endpoints, dtype=torch.float32) / top).to(device)))
            index = torch.as_tensor(fit.index, dtype=torch.float32) / modes.index_top[:, None].to(torch.float32)
            self.weights.append(nn.Parameter(index.to(device)))
            # Buffers, so that .to(device) moves them with the parameters.
            self.register_buffer(f"mode_{number}", torch.as_tensor(fit.mode, device=device))
            self.register_buffer(f"partition_{number}", torch.as_tensor(fit.partition, device=device))
            for field in ("bits", "index_top", "window", "subset"):
                self.register_buffer(f"{field}_{number}", getattr(modes, field).to(device))
            self._two_regions.append(modes.two_regions)
        self._start = np.cumsum([0] + [s.levels for s in self.specs])

    def _index(self, texture: int, level: int) -> int:
        return int(self._start[texture]) + level

    def _modes(self, i: int) -> block_decode.BlockModes:
        return block_decode.BlockModes(*(getattr(self, f"{field}_{i}") for field in
                                         ("bits", "index_top", "window", "subset")), self._two_regions[i])

    def _units(self, i: int) -> tuple[torch.Tensor, block_decode.BlockModes]:
        """Level i's endpoints in their modes' units (the parameters times each block's largest endpoint)."""
        modes = self._modes(i)
        return self.endpoints[i] * modes.top.to(torch.float32)[:, None, None, None], modes

    def level(self, texture: int, level: int) -> torch.Tensor:
        i = self._index(texture, level)
        w, h = self.specs[texture].level_size(level)
        endpoints, modes = self._units(i)
        return block_decode.decode_level(endpoints, self.weights[i], modes, h // 4, w // 4)

    def clamp_(self) -> None:
        """Keep parameters in their stored ranges, and every endpoint within its delta window of the stored
        endpoint 0 (rounding clamps anyway; this stops them drifting far outside, where the straight-through
        gradient would no longer bring them back)."""
        with torch.no_grad():
            for i, (endpoints, weights) in enumerate(zip(self.endpoints, self.weights)):
                weights.clamp_(0.0, 1.0)
                endpoints.clamp_(0.0, 1.0)
                units, modes = self._units(i)
                stored, _ = block_decode.quantize_blocks(units, weights, modes)
                endpoints.copy_(torch.minimum(torch.maximum(units, stored - 0.5), stored + 0.5)
                                / modes.top.to(torch.float32)[:, None, None, None])

    def block_modes(self, texture: int, level: int) -> np.ndarray:
        """The BC6H mode number of every block of one level, (bh, bw) int64."""
        i = self._index(texture, level)
        w, h = self.specs[texture].level_size(level)
        return getattr(self, f"mode_{i}").cpu().numpy().reshape(h // 4, w // 4)

    def blocks(self, texture: int, level: int) -> np.ndarray:
        """The BC6H blocks (bh, bw, 16) uint8 of one level: the quantised parameters encoded as they are."""
        i = self._index(texture, level)
        w, h = self.specs[texture].level_size(level)
        with torch.no_grad():
            units, modes = self._units(i)
            endpoints, index = block_decode.quantize_blocks(units, self.weights[i], modes)
        mode = getattr(self, f"mode_{i}").cpu().numpy()
        fit = partition.BlockFit(mode, endpoints.cpu().numpy(), index.cpu().numpy(),
                                 getattr(self, f"partition_{i}").cpu().numpy(), np.zeros(len(mode)))
        return partition.encode_fit(fit, signed=False).reshape(h // 4, w // 4, bc6h.BLOCK_BYTES)


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


def _feature_range(free: FreeFeatures, texture: int, shared: bool) -> tuple[np.ndarray, np.ndarray]:
    """QUANTILES of all mips of one free feature pyramid: (3,) low and high per channel, or (`shared`) the
    lowest low and highest high of its channels for all three."""
    values = torch.cat([free.level(texture, l).detach().reshape(FEATURE_CHANNELS, -1)
                        for l in range(free.specs[texture].levels)], dim=1).cpu().numpy()
    if values.shape[1] > 1 << 20:  # quantiles of a strided subsample: plenty, and far cheaper
        values = values[:, :: values.shape[1] // (1 << 20) + 1]
    low, high = np.quantile(values, QUANTILES, axis=1)
    if shared:
        low, high = np.full(FEATURE_CHANNELS, low.min()), np.full(FEATURE_CHANNELS, high.max())
    return low, np.maximum(high, low + 1e-6)


def to_block_features(free: FreeFeatures, decoder: Decoder, block_mode: BlockMode,
                      shared_range: bool = False) -> BlockFeatures:
    """Phase 1 -> phase 2 (§5.1): map each feature channel's value range onto STORED_RANGE, fold the inverse map
    into the decoder's input scale/offset (so the MLP sees the same inputs), then fit BC6H blocks to the mapped
    values (`partition.fit_blocks`: the partition search, and with block_mode "auto" each block's best of the
    14 modes). Changes `decoder` in place.

    Ranges are per channel, or with `shared_range` one per texture: then a texture's three channels keep their
    relative scale, and the blocks' line fits weigh them as the decoder does where its inputs are commensurate
    (features initialised from principal components, `fit.pca`)."""
    device = decoder.input_scale.device
    c0, c1 = STORED_RANGE["auto" if block_mode == "auto" else "fixed"]
    fits = []
    scale = decoder.input_scale.detach().cpu().numpy().astype(np.float64)
    offset = decoder.input_offset.detach().cpu().numpy().astype(np.float64)
    modes = encoder_modes(block_mode)
    for i, spec in enumerate(free.specs):
        low, high = _feature_range(free, i, shared_range)
        # The MLP read x (times scale plus offset); it will read c = c0 + (x - low) / (high - low) * (c1 - c0).
        step = (high - low) / (c1 - c0)
        channels = slice(FEATURE_CHANNELS * i, FEATURE_CHANNELS * (i + 1))
        offset[channels] = offset[channels] + scale[channels] * (low - c0 * step)
        scale[channels] = scale[channels] * step
        levels = []
        for level in range(spec.levels):
            x = free.level(i, level).detach().cpu().numpy().astype(np.float64).transpose(1, 2, 0)
            stored = np.clip(c0 + (x - low) / (high - low) * (c1 - c0), c0, c1)
            levels.append(bc6h.image_to_block_texels(stored).reshape(-1, 16, 3))
        # All levels of the pyramid in one call, so that its threads share the work. Without the least-squares
        # refinement: it doubled the transition's time for +0.01 dB of the model's PSNR (Bricks075B and denim,
        # 512, PCA start).
        fit = partition.fit_blocks(np.concatenate(levels), modes, signed=False, refine=False,
                                   workers=torch.get_num_threads())
        bounds = np.cumsum([0] + [len(blocks) for blocks in levels])
        fits += [fit.rows(start, stop) for start, stop in zip(bounds[:-1], bounds[1:])]
    with torch.no_grad():
        decoder.input_scale.copy_(torch.from_numpy(scale))
        decoder.input_offset.copy_(torch.from_numpy(offset))
    return BlockFeatures(free.specs, fits, device)
