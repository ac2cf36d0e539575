"""The two-phase fit of paper §5.1: unconstrained features, the transition to BC6H blocks, block features.

The start is random (the paper's) or the material's principal components (`fit.pca`); the transition fits
blocks of one mode, or of each block's best mode (`to_block_features`). `fit` is then a plain loop per phase:
sample a batch (`fit.batches`), the model G and the reference F(M) at it, MSE (eq. 5), Adam step, learning-rate
decay (exponential or cosine); at the end, phase 2's result or its start, whichever scores better.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import torch

from bcf.core.errors import InputError
from bcf.core.fit.batches import BatchSampler
from bcf.core.fit.model import (BlockFeatures, Decoder, FeatureTextureSpec, FreeFeatures, NeuralMaterial,
                                feature_textures, to_block_features)
from bcf.core.fit.pca import pca_start
from bcf.core.fit.sampling import ReferenceMaterial, texel_centres
from bcf.core.material.texture_set import TextureSet
from bcf.core.options import ResolvedOptions, Schedule
from bcf.core.psnr import psnr_from_mse

__all__ = ["DeviceUnavailableError", "FitResult", "TrainingProgress", "TrainingStopped", "adam_optimizer",
           "centre_error", "fit", "learning_rate_factor", "require_device"]

PROGRESS_INTERVAL_S = 0.5
HISTORY_INTERVAL_S = 2.0
CENTRE_CHUNK = 1 << 16  # texels per forward pass of `centre_error`


@dataclass(frozen=True)
class TrainingProgress:
    """A snapshot for progress displays. psnr is the running training PSNR (dB) of the loss."""

    phase: int
    iteration: int
    total: int
    psnr: float
    iterations_per_s: float
    eta_s: float
    elapsed_s: float


@dataclass(frozen=True)
class HistoryPoint:
    phase: int
    iteration: int
    elapsed_s: float  # since the start of the fit
    psnr: float


class DeviceUnavailableError(InputError):
    """The requested torch device does not exist on this machine."""


def require_device(device: str) -> None:
    """Raise DeviceUnavailableError unless torch can use `device` ("cpu" or "cuda") here."""
    if device == "cuda" and not torch.cuda.is_available():
        raise DeviceUnavailableError(f"device 'cuda' requested, but torch {torch.__version__} sees no CUDA device "
                                     "(a CPU-only build, or no GPU or driver)", fix="use {} cpu",
                                     options=["device"])


class TrainingStopped(Exception):
    """Raised inside `fit` when its `should_stop` callback returns True (cancellation)."""


@dataclass
class FitResult:
    model: NeuralMaterial  # phase-2 model with BlockFeatures (or phase 1's if phase 2 has 0 iterations)
    phase1_model: NeuralMaterial  # snapshot at the end of phase 1 (unconstrained features)
    naive_model: NeuralMaterial  # phase 1's features put in blocks by the transition, before phase 2
    specs: tuple[FeatureTextureSpec, ...]
    phase1_s: float
    transition_s: float
    phase2_s: float
    history: list[HistoryPoint] = field(default_factory=list)
    start_kept: bool = False  # phase 2 ended worse than its start at texel centres, so `model` is the start


ProgressCallback = Callable[[TrainingProgress], None]
StopCallback = Callable[[], bool]
# Called with (phase, iteration, model) every `checkpoint_every` iterations and at the end of each phase
# (benchmarks evaluate the model there; the time it takes is not excluded from the phase timings).
CheckpointCallback = Callable[[int, int, NeuralMaterial], None]


def adam_optimizer(groups: list[dict]) -> torch.optim.Adam:
    """Adam, fused into one kernel per step where this torch build has it for the device (CPU since torch 2.4):
    phase 1 updates millions of free feature texels, and the fused step was 6x faster than the default
    for-each step on 2 cores. The same results, run to run."""
    try:
        return torch.optim.Adam(groups, fused=True)
    except RuntimeError:  # an older torch without a fused CPU Adam
        return torch.optim.Adam(groups)


def learning_rate_factor(schedule: Schedule, decay: float, iteration: int, iterations: int) -> float:
    """The learning rate of the step after `iteration` (of `iterations`) as a fraction of the phase's first:
    decay^iteration, or the cosine from 1 down to 0 at the last iteration (RTXNTC's schedule, fit-levers.md)."""
    if schedule == "cosine":
        return 0.5 * (1.0 + math.cos(math.pi * iteration / max(iterations, 1)))
    return decay**iteration


def _parameter_groups(model: NeuralMaterial, lr_features: float, lr_mlp: float,
                      lr_endpoints: Optional[float]) -> list[dict]:
    """Adam's parameter groups: block endpoints (where they have a rate of their own), the rest of the features,
    the decoder."""
    features = model.features
    if isinstance(features, BlockFeatures) and lr_endpoints is not None:
        return [{"params": list(features.endpoints), "lr": lr_endpoints},
                {"params": list(features.weights), "lr": lr_features},
                {"params": list(model.decoder.parameters()), "lr": lr_mlp}]
    return [{"params": list(features.parameters()), "lr": lr_features},
            {"params": list(model.decoder.parameters()), "lr": lr_mlp}]


def _train_phase(model: NeuralMaterial, batches: BatchSampler, phase: int, iterations: int, schedule: Schedule,
                 lr_features: float, lr_mlp: float, decay: float, start: float, history: list[HistoryPoint],
                 progress: Optional[ProgressCallback],
                 should_stop: Optional[StopCallback], checkpoint: Optional[CheckpointCallback] = None,
                 checkpoint_every: int = 0, lr_endpoints: Optional[float] = None) -> None:
    groups = _parameter_groups(model, lr_features, lr_mlp, lr_endpoints)
    base_lrs = [group["lr"] for group in groups]
    optimizer = adam_optimizer(groups)
    phase_start = time.perf_counter()
    last_report = last_history = phase_start
    running = None
    for iteration in range(1, iterations + 1):
        if should_stop is not None and should_stop():
            raise TrainingStopped(f"stopped in phase {phase} at iteration {iteration - 1}")
        batch = batches()
        loss = torch.mean((model(batch.uv, batch.s) - batch.target) ** 2)  # eq. 5
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if isinstance(model.features, BlockFeatures):
            model.features.clamp_()
        factor = learning_rate_factor(schedule, decay, iteration, iterations)
        for group, base in zip(optimizer.param_groups, base_lrs):
            group["lr"] = base * factor
        # A running mean kept on the device; read back only when reported (a read is a GPU sync).
        running = loss.detach() if running is None else running * 0.95 + loss.detach() * 0.05
        now = time.perf_counter()
        if now - last_history >= HISTORY_INTERVAL_S or iteration == iterations:
            history.append(HistoryPoint(phase, iteration, now - start, psnr_from_mse(float(running))))
            last_history = now
        if progress is not None and (now - last_report >= PROGRESS_INTERVAL_S or iteration == iterations):
            rate = iteration / max(now - phase_start, 1e-9)
            progress(TrainingProgress(phase, iteration, iterations, psnr_from_mse(float(running)), rate,
                                      (iterations - iteration) / rate, now - start))
            last_report = now
        if checkpoint is not None and (iteration == iterations or
                                       (checkpoint_every and iteration % checkpoint_every == 0)):
            checkpoint(phase, iteration, model)


def fit(material: TextureSet, options: ResolvedOptions, progress: Optional[ProgressCallback] = None,
        should_stop: Optional[StopCallback] = None, checkpoint: Optional[CheckpointCallback] = None,
        checkpoint_every: int = 0) -> FitResult:
    """Fit a neural material to `material` with the two-phase schedule of `options`.

    Raises TrainingStopped when `should_stop()` turns True (checked every iteration). CPU runs with the same
    options and seed give identical results.
    """
    require_device(options.device)
    device = torch.device(options.device)
    torch.manual_seed(options.seed)
    generator = torch.Generator(device=device).manual_seed(options.seed)
    # On CPU one generator serves both; on a GPU the per-batch scale comes from its own CPU generator.
    scale_generator = generator if device.type == "cpu" else torch.Generator().manual_seed(options.seed + 1)
    init_generator = torch.Generator().manual_seed(options.seed)
    reference = ReferenceMaterial(material.channels, options.address, device)
    # s and the step kind are needed on the host (they pick the mips), so they come from a CPU generator.
    batches = BatchSampler(reference, options.batch_size, options.continuous_fraction, options.centre_fraction,
                           generator, scale_generator)
    specs = feature_textures(material.width, material.height, options.features)
    history: list[HistoryPoint] = []
    start = time.perf_counter()

    if options.init == "pca":
        free, decoder = pca_start(reference, specs, options.hidden, init_generator)
    else:
        free, decoder = FreeFeatures(specs, init_generator).to(device), Decoder(options.hidden).to(device)
    model = NeuralMaterial(free, decoder, options.address)
    _train_phase(model, batches, 1, options.phase1_iterations, options.schedule, options.lr_features_phase1,
                 options.lr_mlp_phase1, options.decay_phase1, start, history, progress, should_stop, checkpoint,
                 checkpoint_every)
    phase1_s = time.perf_counter() - start
    phase1_model = copy.deepcopy(model)

    t0 = time.perf_counter()
    blocks = to_block_features(free, decoder, options.block_mode, shared_range=options.init == "pca")
    model = NeuralMaterial(blocks, decoder, options.address)
    transition_s = time.perf_counter() - t0
    naive_model = copy.deepcopy(model)  # the "naive BC6" baseline of Fig. 4: compressed after training
    if checkpoint is not None:
        checkpoint(2, 0, model)

    t0 = time.perf_counter()
    _train_phase(model, batches, 2, options.phase2_iterations, options.schedule, options.lr_features_phase2,
                 options.lr_mlp_phase2, options.decay_phase2, start, history, progress, should_stop, checkpoint,
                 checkpoint_every, options.lr_endpoints_phase2)
    # Phase 2 also learns filtering (its continuous and jittered samples) and can end below its start at texel
    # centres, where the start is already close (Metal012 at 2k, 512²: 63.4 dB start, 60.0 after 2,000 steps;
    # docs/BENCHMARKS.md): the fit keeps whichever of the two scores better on the report's measure.
    # (A phase 2 that diverged scores NaN, and so loses too.)
    start_kept = options.phase2_iterations > 0 and not centre_error(model, reference) <= centre_error(naive_model,
                                                                                                      reference)
    if start_kept:
        model = copy.deepcopy(naive_model)
    phase2_s = time.perf_counter() - t0
    return FitResult(model, phase1_model, naive_model, specs, phase1_s, transition_s, phase2_s, history, start_kept)


@torch.no_grad()
def centre_error(model: NeuralMaterial, reference: ReferenceMaterial) -> float:
    """The mean over mips of the MSE at every texel centre of the mip (scale s = mip), of outputs saturated to
    [0, 1] as stored: the measure of the report's aggregate PSNR, in chunks of rows (bounded memory)."""
    errors = []
    for level in range(reference.levels):
        target = reference.mip(level)
        channels, height, width = target.shape
        rows = max(1, CENTRE_CHUNK // width)
        total = 0.0
        for y in range(0, height, rows):
            uv = texel_centres(width, height, slice(y, y + rows), target.device)
            decoded = model(uv, float(level)).clamp(0.0, 1.0)
            expected = target[:, y:y + rows].reshape(channels, -1).t()
            total += float(torch.sum((decoded - expected) ** 2))
        errors.append(total / target.numel())
    return sum(errors) / len(errors)
