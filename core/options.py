"""Compression options: one pydantic model shared by the CLI, the job queue and the HTTP API.

`CompressOptions` is what a user states (a preset plus optional overrides); `resolve_options` turns it into
`ResolvedOptions`, where every value is concrete. The resolved options are what training uses and what the
manifest and report record, so a result always says exactly how it was made.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal, Optional, Sequence

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

__all__ = ["BASELINES", "FEATURE_SCALES", "MAX_BATCH", "MAX_ITERATIONS", "MAX_LEARNING_RATE", "MAX_SEED", "PRESETS",
           "Address", "BaselineSpec", "BlockMode", "CompressOptions", "Device", "FeatureSize", "Init", "JobOptions", "Preset", "ResolvedOptions", "Schedule", "TrainingSchedule",
           "baseline_names", "parse_baselines", "resolve_options"]

Preset = Literal["fast", "default", "paper"]
Address = Literal["wrap", "clamp"]
Device = Literal["cpu", "cuda"]
FeatureSize = Literal["0.5k", "1k", "2k"]
def _block_mode_number(value: object) -> object:
    """"10" and "11" (a command line's strings) as the mode numbers they name."""
    return int(value) if value in ("10", "11") else value


BlockMode = Annotated[Literal[10, 11, "auto"], BeforeValidator(_block_mode_number)]
Init = Literal["random", "pca"]
Schedule = Literal["exponential", "cosine"]
Codec = Literal["bc1_bc5", "astc", "naive_bc6"]  # baseline codecs

# T0's width as a fraction of the material's width; named after the paper's Table 1 for a 2K material.
FEATURE_SCALES: dict[str, float] = {"0.5k": 0.25, "1k": 0.5, "2k": 1.0}


class TrainingSchedule(BaseModel):
    """Everything a preset fixes. Learning rates decay over each phase as `schedule` says: exponentially per
    iteration (lr_t = lr * decay^t) or along a cosine to 0."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    phase1_iterations: int = Field(ge=0, description="iterations with unconstrained features (paper: 5k)")
    phase2_iterations: int = Field(ge=0, description="iterations with BC6H block features (paper: 200k)")
    batch_size: int = Field(ge=256, description="random (u, v) samples per iteration (paper: 512x512)")
    lr_features_phase1: float = Field(gt=0, description="paper: 5e-2")
    lr_mlp_phase1: float = Field(gt=0, description="paper: 1e-3")
    decay_phase1: float = Field(gt=0, le=1, description="paper: 0.9995")
    lr_features_phase2: float = Field(gt=0, description="paper: 1e-2")
    lr_mlp_phase2: float = Field(gt=0, description="paper: 1e-3")
    decay_phase2: float = Field(gt=0, le=1, description="paper: 0.99999")
    # Defaults: the exponential schedule and None, as manifests and reports written before these fields existed
    # were trained.
    schedule: Schedule = Field(
        "exponential", description="learning rates over each phase: exponential (lr * decay^t, the paper's) or "
        "cosine (from lr down to 0 at the phase's last iteration; the decays are then unused)")
    lr_endpoints_phase2: Optional[float] = Field(
        None, gt=0, description="phase-2 rate of the blocks' endpoints (normalised by their largest value); None: "
        "lr_features_phase2, which is always the rate of the blocks' weights (the paper's one feature rate)")
    # Defaults: the paper's sampling, which manifests and reports written before these fields existed used.
    continuous_fraction: float = Field(
        1.0, ge=0, le=1, description="fraction of steps at a continuous scale s (the paper's sampling: 1); the "
        "others sample one integer mip (bcf.core.fit.batches)")
    centre_fraction: float = Field(
        1.0, ge=0, le=1, description="fraction of the integer-mip steps at texel centres, where the target is a "
        "lookup; the others at random points inside the texels")
    hidden: Literal[16, 32] = Field(description="MLP hidden width (paper: 16 or 32)")
    block_mode: BlockMode = Field(
        description="BC6H mode of the feature blocks: 10 = two regions, 6-bit endpoints, 3-bit indices "
                    "(the paper's); 11 = one region, 10-bit endpoints, 4-bit indices; auto = each block in "
                    "whichever of the 14 modes fits it best at the transition")
    # Default: random, as manifests and reports written before this field existed were trained.
    init: Init = Field("random", description="start of the free features and the MLP: random (the paper's), or "
                       "pca: the material's principal components, box-filtered into the pyramids, with the MLP "
                       "set to the inverse projection (bcf.core.fit.pca)")


def _decay(final_ratio: float, iterations: int) -> float:
    """Per-iteration decay that brings the learning rate to final_ratio of its start after `iterations`."""
    return final_ratio ** (1.0 / max(iterations, 1))


# The paper's decays end phase 1 at 0.9995^5000 = 8.2 % and phase 2 at 0.99999^200000 = 13.5 % of the
# starting rate. `fast` and `default` start from the material's principal components and fit each block's
# best BC6H mode, which already beats the former two-phase fit before any training (docs/BENCHMARKS.md, issue 15).
# Phase 1 is skipped (its rates, for users who ask for iterations, are as gentle). `default`'s phase 2 is a
# polish with gentle rates that fall to 0 along a cosine, its samples a quarter at a continuous scale and, of the
# mip steps, half at texel centres: it raises the 1 spp score, and the fit keeps its start where it ends below
# it at texel centres. `fast` is the start alone: 300 polishing steps ended below it on all 7 materials tried.
_POLISH = dict(phase1_iterations=0, lr_features_phase1=2e-3, lr_mlp_phase1=1e-3, decay_phase1=1.0,
               lr_features_phase2=5e-4, lr_endpoints_phase2=5e-5, lr_mlp_phase2=1e-3, decay_phase2=1.0,
               schedule="cosine", continuous_fraction=0.25, centre_fraction=0.5, hidden=16, block_mode="auto",
               init="pca")
PRESETS: dict[str, TrainingSchedule] = {
    "paper": TrainingSchedule(
        phase1_iterations=5000, phase2_iterations=200_000, batch_size=512 * 512,
        lr_features_phase1=5e-2, lr_mlp_phase1=1e-3, decay_phase1=0.9995,
        lr_features_phase2=1e-2, lr_mlp_phase2=1e-3, decay_phase2=0.99999,
        continuous_fraction=1.0, centre_fraction=1.0, hidden=16, block_mode=10),
    # default: measured on the 2K wood material and the 4-material 512² subset (docs/BENCHMARKS.md, issue 15).
    "default": TrainingSchedule(phase2_iterations=2000, batch_size=1 << 16, **_POLISH),
    # fast: the start alone (tests, the demo, previews); the batch is for users who ask for phase-2 iterations.
    "fast": TrainingSchedule(phase2_iterations=0, batch_size=1 << 14, **_POLISH),
}


# Bounds on what a user may ask for, far beyond any useful value, so that nothing a client sends overflows or
# exhausts memory inside the fit: seeds fit torch's 64-bit generators (a GPU fit also uses seed + 1); rates act on
# features and weights of order 1 (the paper's largest is 5e-2); the paper trains 205k iterations of 2^18 samples.
MAX_SEED = 2**63 - 1
MAX_LEARNING_RATE = 1.0
MAX_ITERATIONS = 10_000_000
MAX_BATCH = 1 << 22


class CompressOptions(BaseModel):
    """What the user asks for. Unset schedule fields take the preset's value (`resolve_options`)."""

    model_config = ConfigDict(extra="forbid")

    preset: Preset = Field("default", description="training schedule: fast (tests, demo), default, paper")
    features: FeatureSize = Field("1k", description="T0 at W/4 (0.5k), W/2 (1k) or W (2k)")
    address: Address = Field(
        "wrap", description="texture addressing: wrap for tiling materials, clamp for UV atlases")
    device: Device = Field("cpu", description="where to train")
    seed: int = Field(0, ge=0, le=MAX_SEED, description="random seed")
    phase1_iterations: Optional[int] = Field(None, ge=0, le=MAX_ITERATIONS, description="iterations with unconstrained features "
                                             "(default: the preset's)")
    phase2_iterations: Optional[int] = Field(None, ge=0, le=MAX_ITERATIONS, description="iterations with BC6H block features "
                                             "(default: the preset's)")
    batch_size: Optional[int] = Field(None, ge=256, le=MAX_BATCH, description="samples per iteration (default: the preset's)")
    lr_features_phase1: Optional[float] = Field(None, gt=0, le=MAX_LEARNING_RATE)
    lr_mlp_phase1: Optional[float] = Field(None, gt=0, le=MAX_LEARNING_RATE)
    decay_phase1: Optional[float] = Field(None, gt=0, le=1)
    lr_features_phase2: Optional[float] = Field(None, gt=0, le=MAX_LEARNING_RATE)
    lr_mlp_phase2: Optional[float] = Field(None, gt=0, le=MAX_LEARNING_RATE)
    decay_phase2: Optional[float] = Field(None, gt=0, le=1)
    lr_endpoints_phase2: Optional[float] = Field(None, gt=0, le=MAX_LEARNING_RATE, description="phase-2 rate of the blocks' endpoints "
                                                 "(default: the preset's)")
    schedule: Optional[Schedule] = Field(None, description="learning-rate schedule: exponential or cosine "
                                         "(default: the preset's)")
    continuous_fraction: Optional[float] = Field(None, ge=0, le=1, description="fraction of steps at a continuous "
                                                 "scale; the others at one mip (default: the preset's)")
    centre_fraction: Optional[float] = Field(None, ge=0, le=1, description="fraction of mip steps at texel "
                                             "centres (default: the preset's)")
    hidden: Optional[Literal[16, 32]] = Field(None, description="MLP hidden width (default: the preset's)")
    block_mode: Optional[BlockMode] = Field(None, description="BC6H mode of the feature blocks: 10, 11 or auto "
                                            "(default: the preset's)")
    init: Optional[Init] = Field(None, description="start of the features and the MLP: random or pca (default: the "
                                 "preset's)")

    @model_validator(mode="after")
    def _random_start_needs_phase1(self) -> "CompressOptions":
        """A random start without phase 1 is noise, polished or not: fast and default skip phase 1, which only
        the principal-component start may do."""
        schedule = PRESETS[self.preset]
        init = self.init or schedule.init
        phase1 = schedule.phase1_iterations if self.phase1_iterations is None else self.phase1_iterations
        if init == "random" and phase1 == 0:
            raise ValueError(f"init random needs phase-1 iterations (preset {self.preset} has none: it starts from "
                             "principal components); use preset paper or set phase1_iterations")
        return self


class JobOptions(CompressOptions):
    """One compression as `bcf compress`, the job queue and `POST /v1/jobs` state it: the training options,
    the baseline codecs to score beside ours, and the normal map convention when file names do not say it."""

    baselines: list[str] = Field(default_factory=list, description="baseline codecs to score (names from "
                                 "BASELINES, or the groups all, bc, astc, naive)")
    normal_convention: Optional[Literal["opengl", "directx"]] = Field(
        None, description="green channel convention of the normal map (default: from its file name, else opengl)")

    @field_validator("baselines", mode="before")
    @classmethod
    def _known_baselines(cls, value: object) -> object:
        if isinstance(value, str):
            value = [value]
        if isinstance(value, list) and all(isinstance(v, str) for v in value):
            return parse_baselines(",".join(value)) if value else []
        return value

    def compress_options(self) -> CompressOptions:
        """The training part alone."""
        return CompressOptions(**self.model_dump(exclude={"baselines", "normal_convention"}))


class ResolvedOptions(TrainingSchedule):
    """Every option with its concrete value: the preset's schedule with the user's overrides applied."""

    preset: Preset
    features: FeatureSize
    address: Address
    device: Device
    seed: int


def resolve_options(options: CompressOptions) -> ResolvedOptions:
    """Apply `options`' overrides to its preset's schedule."""
    values = PRESETS[options.preset].model_dump()
    values.update({k: v for k, v in options.model_dump().items() if v is not None})
    return ResolvedOptions(**values)


# ------------------------------------------------------------------------------------------- baselines
# Conventional codecs a compression can be scored against (`bcf.core.report.baselines` runs them).


@dataclass(frozen=True)
class BaselineSpec:
    name: str
    codec: Codec
    half: bool = False  # top mip at half the material's resolution
    block: int = 4  # block side in texels (ASTC n x n)


def _specs() -> dict[str, BaselineSpec]:
    specs = [BaselineSpec(f"bc1_bc5_{r}", "bc1_bc5", r == "half") for r in ("full", "half")]
    specs += [BaselineSpec(f"astc_{n}x{n}_{r}", "astc", r == "half", n) for n in (12, 8, 6) for r in ("full", "half")]
    specs.append(BaselineSpec("naive_bc6", "naive_bc6"))
    return {s.name: s for s in specs}


BASELINES: dict[str, BaselineSpec] = _specs()


def baseline_names(codecs: Sequence[Codec] = ("bc1_bc5", "astc", "naive_bc6")) -> list[str]:
    """Names of the baselines of the given codecs, in BASELINES order."""
    return [name for name, spec in BASELINES.items() if spec.codec in codecs]


BASELINE_GROUPS: dict[str, Sequence[Codec]] = {"all": ("bc1_bc5", "astc", "naive_bc6"), "bc": ("bc1_bc5",),
                                               "astc": ("astc",), "naive": ("naive_bc6",)}


def parse_baselines(text: str) -> list[str]:
    """'all', or a comma-separated list of groups (bc, astc, naive) and names (astc_12x12_full, ...) -> the
    names, in BASELINES order. Raises ValueError naming what is unknown."""
    wanted: set[str] = set()
    for item in (part.strip() for part in text.split(",")):
        if item in BASELINE_GROUPS:
            wanted.update(baseline_names(BASELINE_GROUPS[item]))
        elif item in BASELINES:
            wanted.add(item)
        else:
            raise ValueError(f"unknown baseline {item!r}: use all, bc, astc, naive or names from "
                             f"{', '.join(BASELINES)}")
    return [name for name in BASELINES if name in wanted]
