"""The public pipeline: a texture set in, an export folder with report.json out; and decoding an export
folder back to texture images. The CLI, the job queue and the HTTP service call these two functions.

    TextureSet -> training.fit -> export.write_export -> export.load_export -> metrics.evaluate -> Report
"""

from __future__ import annotations

import datetime
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, Literal, Optional, Sequence

import numpy as np
import torch

from bcf import __version__
from bcf.core import export, images, metrics, report
from bcf.core.material import TextureSet
from bcf.core.options import CompressOptions, ResolvedOptions, resolve_options
from bcf.core.sampling import ReferenceMaterial, material_mip_count
from bcf.core.training import ProgressCallback, StopCallback, fit

__all__ = ["OutputExistsError", "compress_material", "decode_export", "decoded_file_names"]

REPORT_FILE = report.REPORT_FILE
JITTER_SEED = 12345  # fixed, so reports of the same export are identical


class OutputExistsError(ValueError):
    """The output folder exists and is not empty (and overwriting was not asked for)."""


def check_output(output: Path, overwrite: bool) -> None:
    """Refuse early (before any training) to replace a non-empty folder unless `overwrite`."""
    if output.exists() and not output.is_dir():
        raise OutputExistsError(f"{output}: exists and is not a folder")
    if output.is_dir() and any(output.iterdir()) and not overwrite:
        raise OutputExistsError(f"{output}: folder exists and is not empty (use --force to replace it)")


def _replace_folder(staged: Path, output: Path) -> None:
    """Move the finished `staged` folder to `output`, replacing it; `output` is never half-written."""
    if output.exists():
        old = output.with_name(f".{output.name}.old-{os.getpid()}")
        output.rename(old)
        staged.rename(output)
        shutil.rmtree(old, ignore_errors=True)
    else:
        staged.rename(output)


def _mip_sizes(reference: ReferenceMaterial) -> list[tuple[int, int]]:
    return [(m.shape[2], m.shape[1]) for m in reference.mips]


def _evaluate(decoder: metrics.Decoder, reference: ReferenceMaterial,
              jitter_seed: Optional[int] = None) -> report.Evaluation:
    return report.summarise(metrics.evaluate(decoder, reference, jitter_seed), _mip_sizes(reference))


def _folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.iterdir() if p.is_file())


def compress_material(material: TextureSet, options: CompressOptions | ResolvedOptions, output: Path,
                      progress: Optional[ProgressCallback] = None, should_stop: Optional[StopCallback] = None,
                      overwrite: bool = False) -> report.Report:
    """Fit, export to `output` (features_*.dds, decoder.bin, manifest.json, report.json) and evaluate the
    exported files. Work happens in a hidden sibling folder that replaces `output` only when complete, so an
    error or a stop (training.TrainingStopped, KeyboardInterrupt) leaves `output` as it was."""
    started = time.perf_counter()
    resolved = options if isinstance(options, ResolvedOptions) else resolve_options(options)
    output = Path(output)
    check_output(output, overwrite)
    output.parent.mkdir(parents=True, exist_ok=True)
    result = fit(material, resolved, progress, should_stop)

    staged = Path(tempfile.mkdtemp(prefix=f".{output.name}.partial-", dir=output.parent))
    try:
        t0 = time.perf_counter()
        mips = material_mip_count(material.width, material.height)
        export.write_export(staged, result.model, material.source, mips, resolved)
        export_s = time.perf_counter() - t0

        t0 = time.perf_counter()
        exported = export.load_export(staged)
        reference = ReferenceMaterial(material.channels, resolved.address)
        model_cpu = result.model.to("cpu").eval()
        on_files = _evaluate(exported.model, reference)
        models = {"exported": on_files.aggregate,
                  "trained_fp32": _evaluate(model_cpu, reference).aggregate,
                  "phase1_unconstrained": _evaluate(result.phase1_model.to("cpu").eval(), reference).aggregate}
        baseline = report.summarise(metrics.mean_baseline(reference), _mip_sizes(reference)).aggregate
        jittered = _evaluate(exported.model, reference, JITTER_SEED)
        evaluation_s = time.perf_counter() - t0

        manifest = exported.manifest
        features_bytes = sum(t.bytes for t in manifest.feature_textures)
        total = features_bytes + manifest.decoder.bytes
        rep = report.Report(
            generator=f"bcf {__version__}",
            created_at=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            device=_device_name(resolved.device), material=material.source, options=resolved,
            aggregate=on_files.aggregate, per_mip=on_files.per_mip, jittered=jittered, models=models,
            mean_baseline=baseline,
            size=report.SizeReport(total_bytes=total, features_bytes=features_bytes,
                                   weights_bytes=manifest.decoder.bytes, files_bytes=0,
                                   bits_per_texel=total * 8 / (material.width * material.height),
                                   bc1_bc5_bytes=report.bc1_bc5_bytes(material.width, material.height)),
            timing=report.TimingReport(phase1_s=result.phase1_s, transition_s=result.transition_s,
                                       phase2_s=result.phase2_s, export_s=export_s, evaluation_s=evaluation_s,
                                       total_s=time.perf_counter() - started),
            history=[report.HistoryEntry(**vars(h)) for h in result.history])
        # files_bytes counts report.json itself: write once to measure, then with the final number.
        (staged / REPORT_FILE).write_text(rep.model_dump_json(indent=2) + "\n")
        while rep.size.files_bytes != _folder_bytes(staged):  # settles in 1-2 rounds (digit count changes)
            rep.size.files_bytes = _folder_bytes(staged)
            (staged / REPORT_FILE).write_text(rep.model_dump_json(indent=2) + "\n")
        _replace_folder(staged, output)
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        raise
    return rep


def _device_name(device: str) -> str:
    if device == "cuda":
        return f"cuda ({torch.cuda.get_device_name()})"
    return f"cpu ({os.cpu_count()} cores, {torch.get_num_threads()} torch threads)"


# ------------------------------------------------------------------------------------------------ decode


def decoded_file_names(mip: int, extension: str) -> dict[str, str]:
    """Names `decode_export` writes for one mip: albedo.png, ... for mip 0; albedo_mip<N>.png, ... else."""
    suffix = "" if mip == 0 else f"_mip{mip}"
    return {name: f"{name}{suffix}{extension}" for name in ("albedo", "normal", "arm")}


def material_images(channels: np.ndarray) -> dict[str, np.ndarray]:
    """(h, w, 8) decoded material -> albedo, normal (z rebuilt), ARM as (h, w, 3) images in [0, 1]."""
    channels = np.clip(channels, 0.0, 1.0)
    xy = channels[..., 3:5] * 2.0 - 1.0
    z = np.sqrt(np.clip(1.0 - (xy**2).sum(-1, keepdims=True), 0.0, 1.0))
    return {"albedo": channels[..., 0:3], "normal": np.concatenate([channels[..., 3:5], (z + 1.0) / 2.0], -1),
            "arm": channels[..., 5:8]}


def decode_export(folder: Path, output: Path, mips: Sequence[int], extension: Literal[".png", ".exr"] = ".png",
                  png_bits: Literal[8, 16] = 8,
                  on_file: Optional[Callable[[Path], None]] = None) -> list[Path]:
    """The reference decoder: reconstruct albedo / normal / ARM images of the given mips of an export
    folder from its files alone, evaluating at each texel centre of the material mip (scale s = mip).
    Returns the written paths."""
    exported = export.load_export(folder)
    manifest = exported.manifest
    for mip in mips:
        if not 0 <= mip < manifest.mips:
            raise export.ExportError(f"{folder}: mip {mip} does not exist; the material has mips 0..{manifest.mips - 1}")
    output.mkdir(parents=True, exist_ok=True)
    written = []
    for mip in mips:
        w, h = max(1, manifest.width >> mip), max(1, manifest.height >> mip)
        channels = metrics.render_mip(exported.model, w, h, float(mip)).permute(1, 2, 0).numpy()
        for name, image in material_images(channels).items():
            path = output / decoded_file_names(mip, extension)[name]
            images.write_rgb(path, image, png_bits)
            written.append(path)
            if on_file is not None:
                on_file(path)
    return written
