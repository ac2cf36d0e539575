"""The pipeline: a texture set in, an export folder with report.json out, strung through the layers below.

    TextureSet -> fit.training.fit -> export.artifacts.write_export -> export.decode.load_export
               -> report.metrics.evaluate -> report.json / report.html

`result_identity` and `is_current` say whether an earlier result already answers a request (same input
contents, convention, size and options): the job queue, `bcf batch` and `bcf bench` all ask it here.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, Mapping, Optional, Sequence

import torch
from pydantic import BaseModel, ConfigDict

from bcf.core.errors import InputError
from bcf.core.export.artifacts import write_export
from bcf.core.export.decode import DecoderFunction, load_export
from bcf.core.files import replace_folder, staging_folder
from bcf.core.fit.sampling import ReferenceMaterial, material_mip_count
from bcf.core.fit.training import FitResult, ProgressCallback, StopCallback, fit
from bcf.core.material.texture_set import TextureSet
from bcf.core.options import BASELINES, CompressOptions, ResolvedOptions, resolve_options
from bcf.core.report import baselines as baseline_codecs
from bcf.core.report import html as html_report
from bcf.core.report import metrics
from bcf.core.report import report_json as report
from bcf.core.version import GENERATOR

__all__ = ["BASELINES_FOLDER", "OutputExistsError", "OutputNotWritableError", "ResultIdentity", "check_output", "compress_material",
           "is_current", "result_identity"]

BASELINES_FOLDER = "baselines"  # OUT/baselines/<name>/: the baseline codecs' texture files
JITTER_SEED = 12345  # fixed, so reports of the same export are identical
NoteCallback = Callable[[str], None]


class OutputExistsError(InputError):
    """The output folder exists and is not empty (and overwriting was not asked for)."""


class OutputNotWritableError(InputError):
    """The output folder cannot be created or written where it was asked for."""


def check_output(output: Path, overwrite: bool) -> None:
    """Refuse early (before any training) to replace a non-empty folder unless `overwrite`, or to write where
    the result could not be stored: the folder that will hold it is created and a probe folder made in it."""
    if output.exists() and not output.is_dir():
        raise OutputExistsError("exists and is not a folder", file=output)
    if output.is_dir() and any(output.iterdir()) and not overwrite:
        raise OutputExistsError("folder exists and is not empty", file=output, fix="use {} to replace it",
                                options=["force"])
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        os.rmdir(tempfile.mkdtemp(prefix=f".{output.name}.probe-", dir=output.parent))
    except OSError as exc:
        raise OutputNotWritableError(f"cannot write the output here ({exc.strerror or exc})", file=output) from None


# --------------------------------------------------------------------------------------- is it current?


class ResultIdentity(BaseModel):
    """What decides a result: the inputs' contents by role, the normal convention and size they were read with,
    and the resolved options. The device is left out (any device gives an equivalent result)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    files: dict[str, str]  # role -> SHA-256 of the file's bytes
    normal_convention: str
    size: tuple[int, int]  # (width, height) as compressed (a benchmark may box-filter the files down first)
    options: dict  # ResolvedOptions without the device

    def key(self) -> str:
        """A content hash of the identity: equal keys are the same result."""
        return hashlib.sha256(json.dumps(self.model_dump(mode="json"), sort_keys=True).encode()).hexdigest()


def result_identity(files: Mapping[str, str], normal_convention: str, size: tuple[int, int],
                    options: CompressOptions | ResolvedOptions) -> ResultIdentity:
    """The identity of compressing files with these SHA-256 per role, convention and size, with `options`."""
    resolved = options if isinstance(options, ResolvedOptions) else resolve_options(options)
    return ResultIdentity(files=dict(sorted(files.items())), normal_convention=normal_convention, size=size,
                          options=resolved.model_dump(exclude={"device"}))


def _report_identity(rep: report.Report) -> ResultIdentity:
    return result_identity({f.role: f.sha256 for f in rep.material.files}, rep.material.normal_convention,
                           (rep.material.width, rep.material.height), rep.options)


def is_current(rep: report.Report, wanted: ResultIdentity, baselines: Sequence[str] = ()) -> bool:
    """Does the earlier result `rep` answer a request with identity `wanted` and (at least) these baselines?"""
    return _report_identity(rep) == wanted and set(baselines) <= set(rep.baselines)


# ------------------------------------------------------------------------------------------- compress


def _mip_sizes(reference: ReferenceMaterial) -> list[tuple[int, int]]:
    return [(m.shape[2], m.shape[1]) for m in reference.mips]


def _evaluate(decoder: DecoderFunction, reference: ReferenceMaterial,
              jitter_seed: Optional[int] = None) -> report.Evaluation:
    return report.summarise(metrics.evaluate(decoder, reference, jitter_seed), _mip_sizes(reference))


def _folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.iterdir() if p.is_file())


def compress_material(material: TextureSet, options: CompressOptions | ResolvedOptions, output: Path,
                      progress: Optional[ProgressCallback] = None, should_stop: Optional[StopCallback] = None,
                      overwrite: bool = False, baselines: Sequence[str] = (),
                      note: Optional[NoteCallback] = None) -> report.Report:
    """Fit, export to `output` (features_*.dds, decoder.bin, manifest.json, report.json, report.html) and
    evaluate the exported files. `baselines` (names from `options.BASELINES`) are encoded, scored the same
    way into `report.baselines` and written under output/baselines/<name>/; `note` receives a line per stage
    after training. Work happens in a hidden sibling folder that replaces `output` only when complete, so an
    error or a stop (training.TrainingStopped, KeyboardInterrupt) leaves `output` as it was."""
    started = time.perf_counter()
    unknown = [name for name in baselines if name not in BASELINES]
    if unknown:
        raise ValueError(f"unknown baselines {unknown}; known: {', '.join(BASELINES)}")
    say = note or (lambda message: None)
    resolved = options if isinstance(options, ResolvedOptions) else resolve_options(options)
    output = Path(output)
    check_output(output, overwrite)
    output.parent.mkdir(parents=True, exist_ok=True)
    result = fit(material, resolved, progress, should_stop)

    staged = staging_folder(output)
    try:
        t0 = time.perf_counter()
        mips = material_mip_count(material.width, material.height)
        write_export(staged, result.model, material.source, mips, resolved)
        export_s = time.perf_counter() - t0

        say("evaluating the exported files")
        t0 = time.perf_counter()
        exported = load_export(staged)
        reference = ReferenceMaterial(material.channels, resolved.address)
        model_cpu = result.model.to("cpu").eval()
        # One pass over the mips scores every model at texel centres.
        at_centres = metrics.evaluate_at_centres(
            {"exported": exported.model, "trained_fp32": model_cpu,
             "phase1_unconstrained": result.phase1_model.to("cpu").eval()}, reference, mean_baseline=True)
        scores = {name: report.summarise(mips, _mip_sizes(reference)) for name, mips in at_centres.items()}
        on_files, baseline = scores["exported"], scores.pop("mean").aggregate
        models = {name: evaluation.aggregate for name, evaluation in scores.items()}
        jittered = _evaluate(exported.model, reference, JITTER_SEED)
        evaluation_s = time.perf_counter() - t0

        manifest = exported.manifest
        features_bytes = sum(t.bytes for t in manifest.feature_textures)
        total = features_bytes + manifest.decoder.bytes
        decoders: dict[str, DecoderFunction] = {"ours": exported.model}
        baseline_reports = {}
        for name in baselines:
            say(f"baseline {name}: encoding and scoring")
            baseline_reports[name], decoders[name] = _run_baseline(name, material, reference, result, total,
                                                                   staged / BASELINES_FOLDER / name)
        rep = report.Report(
            generator=GENERATOR,
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
                                       total_s=0.0),
            history=[report.HistoryEntry(**vars(h)) for h in result.history], start_kept=result.start_kept,
            baselines=baseline_reports)
        say("writing report.html")
        crops = html_report.select_crops(reference, decoders)
        rep.timing.total_s = time.perf_counter() - started
        html_report.write_html_report(staged / html_report.HTML_REPORT_FILE, rep, crops)
        # files_bytes counts report.json itself: write once to measure, then with the final number.
        (staged / report.REPORT_FILE).write_text(rep.model_dump_json(indent=2) + "\n")
        while rep.size.files_bytes != _folder_bytes(staged):  # settles in 1-2 rounds (digit count changes)
            rep.size.files_bytes = _folder_bytes(staged)
            (staged / report.REPORT_FILE).write_text(rep.model_dump_json(indent=2) + "\n")
        replace_folder(staged, output)
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        raise
    return rep


def _run_baseline(name: str, material: TextureSet, reference: ReferenceMaterial, result: FitResult,
                  our_bytes: int, folder: Path) -> tuple[report.BaselineReport, DecoderFunction]:
    """One baseline's scores and decoder; naive_bc6 is the fit's transition snapshot, the same size as ours."""
    if name != "naive_bc6":
        return baseline_codecs.run_codec_baseline(name, material.channels, reference, folder)
    naive = result.naive_model.to("cpu").eval()
    scored = baseline_codecs.evaluate_baseline(
        "our phase-1 features (or the principal-component start) put in BC6H blocks by the transition, no phase 2 "
        "(paper Fig. 4)", "bcf block fit", material.width, material.height, naive, our_bytes,
        result.transition_s, reference)
    return scored, naive


def _device_name(device: str) -> str:
    if device == "cuda":
        return f"cuda ({torch.cuda.get_device_name()})"
    return f"cpu ({os.cpu_count()} cores, {torch.get_num_threads()} torch threads)"
