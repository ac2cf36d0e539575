"""`bcf batch`: compress every material of an asset folder, locally or on the HTTP service (thin layer over
bcf.jobs.batch and bcf.service.client).

Exit codes: 0 every material compressed or up to date, 1 some material failed (the others were done), 2 user
error (no such folder, nothing found, bad options, service unreachable), 130 interrupted (the summary is written;
running again continues).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Callable, Optional, TextIO

from cyclopts import Parameter
from cyclopts.types import PositiveInt

from bcf.cli import OptionalOutput, Quiet, clock, model_flags
from bcf.core import InputError, JobOptions

if TYPE_CHECKING:
    from bcf.core import AssetScan
    from bcf.jobs.batch import BatchItem, BatchMaterial, MaterialEvent

# ------------------------------------------------------------------------------------------------- list


def _print_json(scan: "AssetScan") -> None:
    print(json.dumps([m.model_dump(mode="json", exclude={"output", "notes"}) for m in scan.materials], indent=2))
    for u in scan.unplaced:
        print(f"bcf: not placed: {u.path}: {u.reason}", file=sys.stderr)


def _print_list(scan: "AssetScan") -> None:
    for m in scan.materials:
        size = f"{m.resolution[0]}x{m.resolution[1]}" if m.resolution else "size unknown"
        print(f"{m.material}  ({m.dir}, {size}, normal {m.normal_convention or 'convention unknown'})")
        for role, path in m.files.items():
            print(f"  {role:<10} {path}")
        for problem in m.problems:
            print(f"  problem: {problem}")
        for note in m.notes:
            print(f"  note: {note}")
    if scan.unplaced:
        print(f"not placed ({len(scan.unplaced)}):")
        for u in scan.unplaced:
            print(f"  {u.path}: {u.reason}")
    complete = sum(not m.problems for m in scan.materials)
    print(f"{len(scan.materials)} materials ({complete} complete), {len(scan.unplaced)} files not placed")


# --------------------------------------------------------------------------------------------- progress


class BatchProgress:
    """Overall progress (done / total, failures, ETA) and a line per running material (phase, iteration).
    On a terminal the block is redrawn in place; otherwise a line per start / finish and a status line every
    30 s. Safe to call from the event thread of parallel runs."""

    def __init__(self, total: int, jobs: int, stream: TextIO = sys.stderr):
        self.total, self.jobs, self.stream = total, jobs, stream
        self.tty = stream.isatty()
        self.running: dict[str, str] = {}
        self.finished: list["BatchItem"] = []
        self.started = time.monotonic()
        self.lock = threading.Lock()
        self.drawn = 0
        self.last_draw = self.last_status = 0.0

    def __call__(self, event: "MaterialEvent") -> None:
        with self.lock:
            if event.kind == "started":
                self.running[event.material] = "starting"
                if not self.tty:
                    self._line(f"started {event.material}")
            elif event.kind == "progress" and event.material in self.running and event.stage:
                self.running[event.material] = event.stage
            elif event.kind == "progress" and event.material in self.running and event.progress:
                p = event.progress
                self.running[event.material] = (f"phase {p.phase}/2 {p.iteration}/{p.total} {p.psnr:5.2f} dB "
                                                f"ETA {clock(p.eta_s)}")
            elif event.kind == "finished" and event.item is not None:
                self.running.pop(event.material, None)
                self.finished.append(event.item)
                if not self.tty:
                    self._line(f"{event.item.status} {event.material}" + _outcome(event.item))
            self._draw(force=event.kind != "progress" or event.stage is not None)

    def _overall(self) -> str:
        done = len(self.finished)
        failed = sum(i.status == "failed" for i in self.finished)
        worked = [i.seconds for i in self.finished if i.status == "compressed" and i.seconds]
        eta = (f", ETA {clock(sum(worked) / len(worked) * (self.total - done) / max(self.jobs, 1))}"
               if worked and done < self.total else "")
        return (f"batch: {done}/{self.total} done" + (f", {failed} failed" if failed else "") +
                f", {len(self.running)} running, {clock(time.monotonic() - self.started)} elapsed{eta}")

    def _draw(self, force: bool) -> None:
        now = time.monotonic()
        if not self.tty:
            if now - self.last_status >= 30.0:
                self._line(self._overall() + "".join(f"\n  {n}: {s}" for n, s in self.running.items()))
                self.last_status = now
            return
        if not force and now - self.last_draw < 0.2:
            return
        lines = [self._overall()] + [f"  {name}: {state}" for name, state in self.running.items()]
        up = f"\x1b[{self.drawn}F" if self.drawn else ""
        self.stream.write(up + "\x1b[J" + "\n".join(lines) + "\n")
        self.stream.flush()
        self.drawn, self.last_draw = len(lines), now

    def _line(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()


def _outcome(item: "BatchItem") -> str:
    if item.status == "failed":
        return f": {item.error}"
    if item.psnr is not None:
        return f": {item.psnr:.2f} dB, {item.size_bytes / 1024:.1f} KiB, {item.seconds:.1f} s"
    return ""


# ---------------------------------------------------------------------------------------------- command


def batch(assets_dir: Path, /, *, output: OptionalOutput = None,
          list_only: Annotated[bool, Parameter(name="--list")] = False,
          as_json: Annotated[bool, Parameter(name="--json")] = False,
          options: Annotated[JobOptions, model_flags("preset", "features", "address", "baselines", "phase1_iterations",
                                                     "phase2_iterations", "batch_size", "device")] = JobOptions(),
          jobs: Annotated[PositiveInt, Parameter(name=["-j", "--jobs"])] = 1, force: bool = False,
          submit: Optional[str] = None, token: Annotated[Optional[str], Parameter(env_var="BCF_TOKEN")] = None,
          quiet: Quiet = False) -> int:
    """Compress every material found in an asset folder (resumable), locally or on the HTTP service, with a
    summary.

    Texture sets are found by their file names (Poly Haven, ambientCG, 3dtextures.me, Substance Painter, glTF
    ORM, Unreal _D/_N/_ORM); OUT_DIR mirrors the input tree, one bcf compress folder per material, plus
    batch-summary.json. A material whose inputs and options are unchanged since its last successful output is
    skipped. Exit codes: 0 all done, 1 some material failed, 2 user error, 130 interrupted.

    Args:
        assets_dir: folder tree of texture sets
        output: output folder (required unless --list)
        list_only: only show what was found (material, role -> file, normal convention, resolution) and what could
            not be placed
        as_json: with --list: print it as JSON for scripts
        options.device: local runs only
        jobs: materials compressed at once, in separate processes sharing the cores
        force: recompress materials that are up to date
        submit: send the materials to a bcf service (bcf serve) at this URL and download the results instead
            of compressing here
        token: bearer token for --submit
    """
    from bcf.core import require_device, scan_assets
    from bcf.jobs import batch as jobs_batch

    if not assets_dir.is_dir():
        raise InputError("no such folder", file=assets_dir)
    if as_json and not list_only:
        raise InputError("{} goes with {}", options=["json", "list"])
    scan = scan_assets(assets_dir)
    if list_only:
        (_print_json if as_json else _print_list)(scan)
        return 0
    if output is None:
        raise InputError("-o OUT_DIR is required (or use --list)")
    if not scan.materials:
        raise InputError("no texture sets found (files named like *_diff/_nor_gl/_arm, *_Color/_NormalGL/_Roughness, "
                         "*_BaseColor/_Normal/_OcclusionRoughnessMetallic, ...); try --list", file=assets_dir)
    if not submit:
        require_device(options.device)
    started_at, started = jobs_batch.now_iso(), time.perf_counter()
    plan = jobs_batch.plan_batch(scan, assets_dir, output)
    todo, skipped = jobs_batch.split_done(plan, options, force)
    print(f"bcf batch: {len(plan)} materials in {assets_dir}: {len(skipped)} up to date, {len(todo)} to "
          f"{'submit to ' + submit if submit else 'compress'}"
          + (f" ({jobs} at a time)" if len(todo) > 1 and jobs > 1 and not submit else ""), flush=True)
    if scan.unplaced:
        print(f"  {len(scan.unplaced)} files not placed (see --list)", flush=True)
    display = None if quiet else BatchProgress(len(todo), 1 if submit else jobs)
    finished: dict[str, "BatchItem"] = {}

    def on_event(event: "MaterialEvent") -> None:
        if event.kind == "finished" and event.item is not None:
            finished[event.item.output] = event.item
        if display is not None:
            display(event)

    interrupted = False
    try:
        items = _remote(todo, options, submit, token, on_event) if submit else jobs_batch.run_local(
            todo, options, jobs, on_event)
    except KeyboardInterrupt:
        interrupted = True
        items = [finished.get(e.output_name) or _after_interrupt(e, options) for e in todo]
    summary = jobs_batch.summarise(assets_dir, output, "submit" if submit else "local", options, started_at,
                                   time.perf_counter() - started, [*skipped, *items])
    path = jobs_batch.write_summary(output, summary)
    print(jobs_batch.format_summary(summary))
    print(f"wrote {path}")
    if interrupted:
        raise KeyboardInterrupt("finished materials are kept, run the same command again to continue")
    return 1 if summary.counts["failed"] else 0


def _after_interrupt(entry: "BatchMaterial", options: JobOptions) -> "BatchItem":
    """A material the interrupt caught: finished if its output was completed just before (the result is in
    place even if the display never heard of it), else interrupted."""
    from bcf.jobs.batch import previous_result, result_item

    previous = previous_result(entry, options)
    return entry.item("interrupted") if previous is None else result_item(entry, previous, "compressed", 0.0)


def _remote(todo: "list[BatchMaterial]", options: JobOptions, url: str, token: Optional[str],
            on_event: "Callable[[MaterialEvent], None]") -> "list[BatchItem]":
    from bcf.service.client import ServiceClient, ServiceUnavailable, run_remote

    client = ServiceClient(url, token)
    try:
        return run_remote(todo, options, client, on_event)
    except ServiceUnavailable as exc:
        raise InputError(str(exc)) from None
    finally:
        client.close()


COMMANDS = (batch,)
