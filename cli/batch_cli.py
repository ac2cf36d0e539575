"""`bcf batch`: compress every material of an asset folder (thin layer over bcf.core.batch).

Exit codes: 0 every material compressed or up to date, 1 some material failed (the others were done), 2 user
error (no such folder, nothing found, bad options, service unreachable), 130 interrupted (the summary is written;
running again continues).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, TextIO

from bcf.material_cli import cli_message

if TYPE_CHECKING:
    from bcf.core.material.assets import AssetScan
    from bcf.jobs.batch import BatchItem, MaterialEvent

COMMAND = ("compress every material found in an asset folder (resumable), locally or on the HTTP service, "
           "with a summary")


def add_commands(commands: argparse._SubParsersAction, user_error: type[Exception],
                 positive_int: Callable[[str], int], non_negative_int: Callable[[str], int]) -> None:
    p = commands.add_parser(
        "batch", help=COMMAND, description=COMMAND + ".",
        epilog="Texture sets are found by their file names (Poly Haven, ambientCG, 3dtextures.me, Substance Painter, "
               "glTF ORM, Unreal _D/_N/_ORM); OUT_DIR mirrors the input tree, one bcf compress folder per material, "
               "plus batch-summary.json. A material whose inputs and options are unchanged since its last "
               "successful output is skipped. Exit codes: 0 all done, 1 some material failed, 2 user error, "
               "130 interrupted.")
    p.add_argument("assets", metavar="ASSETS_DIR", help="folder tree of texture sets")
    p.add_argument("-o", "--output", metavar="OUT_DIR", help="output folder (required unless --list)")
    p.add_argument("--list", action="store_true", help="only show what was found (material, role -> file, normal "
                                                       "convention, resolution) and what could not be placed")
    p.add_argument("--json", action="store_true", help="with --list: print it as JSON for scripts")
    p.add_argument("--preset", choices=("fast", "default", "paper"), default="default")
    p.add_argument("--features", choices=("0.5k", "1k", "2k"), default="1k")
    p.add_argument("--address", choices=("wrap", "clamp"), default="wrap")
    p.add_argument("--baselines", metavar="LIST", help="also score baselines, as for 'bcf compress --baselines'")
    p.add_argument("--phase1-iterations", type=non_negative_int, metavar="N")
    p.add_argument("--phase2-iterations", type=non_negative_int, metavar="N")
    p.add_argument("--batch-size", type=positive_int, metavar="N")
    p.add_argument("-j", "--jobs", type=positive_int, default=1, metavar="N",
                   help="materials compressed at once, in separate processes sharing the cores (default: 1)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="local runs only")
    p.add_argument("--force", action="store_true", help="recompress materials that are up to date")
    p.add_argument("--submit", metavar="URL", help="send the materials to a bcf service (bcf serve) and download "
                                                   "the results instead of compressing here")
    p.add_argument("--token", metavar="T", default=os.environ.get("BCF_TOKEN"),
                   help="bearer token for --submit (default: $BCF_TOKEN)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    p.set_defaults(handler=functools.partial(_batch, user_error=user_error))


# ------------------------------------------------------------------------------------------------- list


def _listing(scan: "AssetScan") -> list[dict]:
    return [{"material": m.material, "dir": m.dir, "files": dict(m.files), "normal_convention": m.normal_convention,
             "resolution": list(m.resolution) if m.resolution else None, "problems": list(m.problems)}
            for m in scan.materials]


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


def _clock(seconds: float) -> str:
    seconds = int(round(max(seconds, 0.0)))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


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
                                                f"ETA {_clock(p.eta_s)}")
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
        eta = (f", ETA {_clock(sum(worked) / len(worked) * (self.total - done) / max(self.jobs, 1))}"
               if worked and done < self.total else "")
        return (f"batch: {done}/{self.total} done" + (f", {failed} failed" if failed else "") +
                f", {len(self.running)} running, {_clock(time.monotonic() - self.started)} elapsed{eta}")

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


def _options(args: argparse.Namespace):
    from bcf.core.options import parse_baselines
    from bcf.core.material.roles import MaterialError
    from bcf.core.options import JobOptions

    try:
        baselines = parse_baselines(args.baselines) if args.baselines else []
    except ValueError as exc:
        raise MaterialError(f"--baselines: {exc}") from None
    overrides = {k: getattr(args, k) for k in ("phase1_iterations", "phase2_iterations", "batch_size")
                 if getattr(args, k) is not None}
    return JobOptions(preset=args.preset, features=args.features, address=args.address, device=args.device,
                      baselines=baselines, **overrides)


def _batch(args: argparse.Namespace, user_error: type[Exception]) -> int:
    from bcf.core.material import assets
    from bcf.jobs import batch
    from bcf.core.material.roles import MaterialError

    root = Path(args.assets)
    if not root.is_dir():
        raise user_error(f"{root}: no such folder")
    if args.json and not args.list:
        raise user_error("--json goes with --list")
    scan = assets.scan_assets(root)
    if args.list:
        if args.json:
            print(json.dumps(_listing(scan), indent=2))
            for u in scan.unplaced:
                print(f"bcf: not placed: {u.path}: {u.reason}", file=sys.stderr)
        else:
            _print_list(scan)
        return 0
    if args.output is None:
        raise user_error("-o OUT_DIR is required (or use --list)")
    if not scan.materials:
        raise user_error(f"{root}: no texture sets found (files named like *_diff/_nor_gl/_arm, *_Color/_NormalGL/"
                         "_Roughness, *_BaseColor/_Normal/_OcclusionRoughnessMetallic, ...); try --list")
    try:
        options = _options(args)
    except MaterialError as exc:
        raise user_error(cli_message(exc)) from None
    if args.device == "cuda" and not args.submit:
        import torch

        if not torch.cuda.is_available():
            raise user_error(f"--device cuda: torch {torch.__version__} sees no CUDA device; use --device cpu")
    output = Path(args.output)
    started_at, started = batch.now_iso(), time.perf_counter()
    plan = batch.plan_batch(scan, root, output)
    todo, skipped = batch.split_done(plan, options, args.force)
    print(f"bcf batch: {len(plan)} materials in {root}: {len(skipped)} up to date, {len(todo)} to "
          f"{'submit to ' + args.submit if args.submit else 'compress'}"
          + (f" ({args.jobs} at a time)" if len(todo) > 1 and args.jobs > 1 and not args.submit else ""),
          flush=True)
    if scan.unplaced:
        print(f"  {len(scan.unplaced)} files not placed (see --list)", flush=True)
    display = None if args.quiet else BatchProgress(len(todo), 1 if args.submit else args.jobs)
    finished: dict[str, "BatchItem"] = {}

    def on_event(event: "MaterialEvent") -> None:
        if event.kind == "finished" and event.item is not None:
            finished[event.item.output] = event.item
        if display is not None:
            display(event)

    interrupted = False
    try:
        if args.submit:
            from bcf.service.client import ServiceClient, ServiceUnavailable

            client = ServiceClient(args.submit, args.token)
            try:
                batch_items = _remote(todo, options, client, on_event, user_error, ServiceUnavailable)
            finally:
                client.close()
        else:
            batch_items = batch.run_local(todo, options, args.jobs, on_event)
    except KeyboardInterrupt:
        interrupted = True
        batch_items = [finished.get(e.output_name) or _after_interrupt(e, options) for e in todo]
    summary = batch.summarise(root, output, "submit" if args.submit else "local", options, started_at,
                              time.perf_counter() - started, [*skipped, *batch_items])
    path = batch.write_summary(output, summary)
    print(batch.format_summary(summary))
    print(f"wrote {path}")
    if interrupted:
        print("bcf: interrupted; finished materials are kept, run the same command again to continue",
              file=sys.stderr)
        return 130
    return 1 if summary.counts["failed"] else 0


def _after_interrupt(entry, options) -> "BatchItem":
    """A material the interrupt caught: finished if its output was completed just before (the result is in
    place even if the display never heard of it), else interrupted."""
    from bcf.jobs import batch

    previous = batch.previous_result(entry, options)
    return entry.item("interrupted") if previous is None else batch.result_item(entry, previous, "compressed", 0.0)


def _remote(todo, options, client, on_event, user_error, unavailable):
    from bcf.service.client import run_remote

    try:
        return run_remote(todo, options, client, on_event)
    except unavailable as exc:
        raise user_error(cli_message(exc)) from None
