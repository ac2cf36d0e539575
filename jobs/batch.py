"""`bcf batch`: compress every material of an asset folder, resumably, reporting each one's outcome.

The scan (`assets.scan_assets`) finds the materials; `plan_batch` gives each its output folder (mirroring the
input tree); `previous_result` decides what an earlier run already did; `run_local` compresses the rest here
(one material at a time, or `jobs` worker processes). `bcf batch --submit` uses the same plan and summary with
the HTTP service doing the work (`bcf.service.client.run_remote`). A failing material becomes a `failed` item;
the others go on.
"""

from __future__ import annotations

import datetime
import multiprocessing
import os
import queue as queue_module
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal, Optional, Sequence

from pydantic import BaseModel

from bcf.core import (GENERATOR, MANIFEST_FILE, AssetScan, FoundMaterial, JobOptions, MaterialError, MaterialFiles,
                      OutputExistsError, Report, ReportError, TrainingProgress, compress_material, failure_text,
                      file_sha256, is_current, load_texture_set, read_report, result_identity, write_text_atomic)

__all__ = ["BATCH_SUMMARY_FILE", "BatchItem", "BatchMaterial", "BatchSummary", "MaterialEvent", "format_summary",
           "plan_batch", "previous_result", "run_local", "split_done", "summarise", "write_summary"]

BATCH_SUMMARY_FILE = "batch-summary.json"
Status = Literal["compressed", "skipped", "failed", "interrupted"]


class BatchItem(BaseModel):
    """One material's outcome."""

    material: str
    dir: str  # input folder, relative to the assets root
    output: str  # output folder, relative to the batch output folder
    status: Status
    psnr: Optional[float] = None  # aggregate PSNR (dB) of the exported files, from report.json
    ssim: Optional[float] = None
    size_bytes: Optional[int] = None  # feature textures + decoder weights
    seconds: Optional[float] = None  # wall time of this run's work on it (0 when skipped)
    error: Optional[str] = None
    job_id: Optional[str] = None  # with --submit: the service's job


class BatchSummary(BaseModel):
    generator: str
    root: str
    output: str
    mode: Literal["local", "submit"]
    options: JobOptions
    started_at: str
    seconds: float
    counts: dict[str, int]
    items: list[BatchItem]


@dataclass(frozen=True)
class BatchMaterial:
    """A found material with absolute paths: its files and where its result goes."""

    found: FoundMaterial
    files: MaterialFiles
    output: Path
    output_name: str  # relative to the batch output folder, POSIX

    def item(self, status: Status, **values: object) -> BatchItem:
        return BatchItem(material=self.found.material, dir=self.found.dir, output=self.output_name, status=status,
                         **values)


@dataclass(frozen=True)
class MaterialEvent:
    """For progress displays: a material started, progressed (training) or finished (with its item)."""

    material: str
    kind: Literal["started", "progress", "finished"]
    progress: Optional[TrainingProgress] = None
    item: Optional[BatchItem] = None
    stage: Optional[str] = None  # after training: "evaluating the exported files", "writing report.html", ...


EventCallback = Callable[[MaterialEvent], None]


# ---------------------------------------------------------------------------------------------- planning


def _output_names(found: Sequence[FoundMaterial], root_name: str) -> list[str]:
    """Each material's output folder, relative: its `output`, except that a folder's result must never
    contain another's (compress replaces its folder whole), so a material whose output is an ancestor of
    another's (a material folder with material sub-folders, or the root itself) goes one level down, into a
    folder named after itself."""
    names = [m.output for m in found]

    def placed(name: str) -> str:
        if name == ".":
            return root_name
        if any(other.startswith(name + "/") for other in names):
            return f"{name}/{Path(name).name}"
        return name

    return [placed(name) for name in names]


def plan_batch(scan: AssetScan, root: Path, output: Path) -> list[BatchMaterial]:
    root, output = Path(root).resolve(), Path(output).resolve()
    names = _output_names(scan.materials, root.name)
    return [BatchMaterial(found=m, files=m.material_files(root), output=output / name, output_name=name)
            for m, name in zip(scan.materials, names)]


def previous_result(entry: BatchMaterial, options: JobOptions) -> Optional[Report]:
    """The report of an earlier output of this material that is still current (`bcf.core.is_current`: same file
    contents, convention, size and options, at least the wanted baselines); else None."""
    if entry.found.resolution is None:
        return None
    try:
        previous = read_report(entry.output)
        hashes = {role: file_sha256(Path(path)) for role, path in entry.files.roles().items()}
    except (ReportError, OSError):
        return None
    wanted = result_identity(hashes, entry.files.normal_convention or "opengl", tuple(entry.found.resolution),
                             options.compress_options())
    return previous if is_current(previous, wanted, options.baselines) else None


def result_item(entry: BatchMaterial, rep: Report, status: Status, seconds: float,
                **values: object) -> BatchItem:
    return entry.item(status, psnr=rep.aggregate.psnr.all, ssim=rep.aggregate.ssim.all,
                      size_bytes=rep.size.total_bytes, seconds=round(seconds, 2), **values)


def split_done(plan: Sequence[BatchMaterial], options: JobOptions,
               force: bool) -> tuple[list[BatchMaterial], list[BatchItem]]:
    """(materials to run, items of those skipped because their output is up to date). Incomplete materials
    are run, so that they fail with their problem named."""
    todo, skipped = [], []
    for entry in plan:
        previous = None if force or entry.found.problems else previous_result(entry, options)
        if previous is None:
            todo.append(entry)
        else:
            skipped.append(result_item(entry, previous, "skipped", 0.0))
    return todo, skipped


def check_replaceable(output: Path) -> None:
    """Only an earlier bcf result (or an empty folder) may be replaced: never a user's own folder."""
    if output.is_dir() and any(output.iterdir()) and not (output / MANIFEST_FILE).is_file():
        raise OutputExistsError(f"{output}: exists and is not a bcf output folder; move it away")


# ------------------------------------------------------------------------------------------------ local


def compress_one(entry: BatchMaterial, options: JobOptions,
                 on_progress: Optional[Callable[[TrainingProgress], None]] = None,
                 on_stage: Optional[Callable[[str], None]] = None) -> BatchItem:
    """Compress one material into its output folder; any failure becomes a `failed` item."""
    started = time.perf_counter()
    try:
        if entry.found.problems:
            raise MaterialError("; ".join(entry.found.problems))
        check_replaceable(entry.output)
        texture_set = load_texture_set(entry.files, name=entry.found.material.replace("/", "_"))
        rep = compress_material(texture_set, options.compress_options(), entry.output, progress=on_progress,
                                overwrite=True, baselines=options.baselines, note=on_stage)
    except Exception as exc:  # one material's failure is reported, the batch goes on
        return entry.item("failed", error=failure_text(exc), seconds=round(time.perf_counter() - started, 2))
    return result_item(entry, rep, "compressed", time.perf_counter() - started)


def _compress_in_process(entry: BatchMaterial, options: JobOptions, events: "queue_module.Queue[MaterialEvent]",
                         threads: int) -> BatchItem:
    """`compress_one` in a worker process of `run_local`, its events sent back through `events` (a manager's
    queue, so it travels as an argument) and its share of the cores set first."""
    import torch

    torch.set_num_threads(threads)
    name = entry.found.material
    events.put(MaterialEvent(name, "started"))
    item = compress_one(entry, options, lambda p: events.put(MaterialEvent(name, "progress", p)),
                        lambda stage: events.put(MaterialEvent(name, "progress", stage=stage)))
    # Sent from here, on the same queue as "started", so a display never sees the next material start first.
    events.put(MaterialEvent(name, "finished", item=item))
    return item


def run_local(todo: Sequence[BatchMaterial], options: JobOptions, jobs: int = 1,
              events: Optional[EventCallback] = None) -> list[BatchItem]:
    """Compress `todo` here: in this process when `jobs` is 1, else in `jobs` processes with the cores split
    between them. Items come back in the order of `todo`."""
    emit = events or (lambda event: None)
    if jobs <= 1 or len(todo) <= 1:
        items = []
        for entry in todo:
            emit(MaterialEvent(entry.found.material, "started"))
            name = entry.found.material
            item = compress_one(entry, options, lambda p, n=name: emit(MaterialEvent(n, "progress", p)),
                                lambda stage, n=name: emit(MaterialEvent(n, "progress", stage=stage)))
            emit(MaterialEvent(entry.found.material, "finished", item=item))
            items.append(item)
        return items
    context = multiprocessing.get_context("spawn")  # fork after torch threads started is unsafe
    threads = max(1, (os.cpu_count() or 1) // jobs)
    done: dict[int, BatchItem] = {}
    with context.Manager() as manager:
        messages = manager.Queue()
        pump = threading.Thread(target=_pump, args=(messages, emit), daemon=True)
        pump.start()
        try:
            with ProcessPoolExecutor(jobs, mp_context=context) as pool:
                futures: dict[Future, int] = {pool.submit(_compress_in_process, entry, options, messages, threads): i
                                              for i, entry in enumerate(todo)}
                pending = set(futures)
                while pending:
                    finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for future in finished:
                        index = futures[future]
                        entry = todo[index]
                        try:
                            item = future.result()
                        except Exception as exc:  # the worker process itself died: nobody announced the end
                            item = entry.item("failed", error=f"worker process failed: {failure_text(exc)}")
                            messages.put(MaterialEvent(entry.found.material, "finished", item=item))
                        done[index] = item
        finally:
            messages.put(None)
            pump.join(timeout=5)
    return [done[i] for i in range(len(todo))]


def _pump(messages: "queue_module.Queue[Optional[MaterialEvent]]", emit: EventCallback) -> None:
    """Forward the worker processes' events, in arrival order, to the display."""
    while True:
        try:
            event = messages.get(timeout=1.0)
        except queue_module.Empty:
            continue
        if event is None:
            return
        emit(event)


# ---------------------------------------------------------------------------------------------- summary


def summarise(root: Path, output: Path, mode: Literal["local", "submit"], options: JobOptions, started_at: str,
              seconds: float, items: Sequence[BatchItem]) -> BatchSummary:
    ordered = sorted(items, key=lambda item: item.output)
    counts = {status: sum(item.status == status for item in ordered)
              for status in ("compressed", "skipped", "failed", "interrupted")}
    return BatchSummary(generator=GENERATOR, root=str(Path(root).resolve()),
                        output=str(Path(output).resolve()), mode=mode, options=options, started_at=started_at,
                        seconds=round(seconds, 2), counts=counts, items=ordered)


def now_iso() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def write_summary(output: Path, summary: BatchSummary) -> Path:
    return write_text_atomic(Path(output) / BATCH_SUMMARY_FILE, summary.model_dump_json(indent=2) + "\n")


def format_summary(summary: BatchSummary) -> str:
    """The end-of-run table: material, status, PSNR, size, time; then the errors in full."""
    rows = [("material", "status", "PSNR dB", "size KiB", "time s")]
    for item in summary.items:
        rows.append((item.material, item.status, f"{item.psnr:.2f}" if item.psnr is not None else "-",
                     f"{item.size_bytes / 1024:.1f}" if item.size_bytes is not None else "-",
                     f"{item.seconds:.1f}" if item.seconds is not None else "-"))
    widths = [max(len(row[i]) for row in rows) for i in range(5)]
    lines = ["  ".join(cell.ljust(w) if i < 2 else cell.rjust(w) for i, (cell, w) in enumerate(zip(row, widths)))
             for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    counts = ", ".join(f"{n} {status}" for status, n in summary.counts.items() if n)
    lines.append(f"{len(summary.items)} materials: {counts or 'none'} in {summary.seconds:.0f} s")
    for item in summary.items:
        if item.error:
            lines.append(f"  {item.material}: {item.error}")
    return "\n".join(lines)
