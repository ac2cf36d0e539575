"""Worker processes kept alive beside the API (`bcf serve --workers N`): a dead worker is reaped and replaced,
with a growing pause when it keeps dying, and every worker ends with the process that started it.

A worker killed mid-job loses nothing: its job's record goes stale and the next worker re-runs it
(`bcf.jobs.worker`). The supervisor only makes sure that a next worker exists.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

__all__ = ["WorkerStatus", "WorkerSupervisor", "exit_with_parent"]

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def exit_with_parent(parent_pid: int) -> None:
    """Ask the kernel to send this process SIGTERM when its parent ends (Linux; elsewhere nothing), and end at
    once if the parent `parent_pid` has already gone. A worker of `bcf serve` calls this first, so that a
    `kill -9` of the server leaves no worker consuming the queue on its own."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), signal.SIGTERM)


@dataclass(frozen=True)
class WorkerStatus:
    wanted: int  # workers the supervisor keeps
    live: int  # of them running now
    restarts: int  # replacements started since the supervisor started


@dataclass
class _Slot:
    process: Optional[subprocess.Popen[bytes]] = None
    started: float = 0.0
    failures: int = 0  # deaths in a row, each soon after its start
    restart_at: Optional[float] = None


class WorkerSupervisor:
    """Keeps `count` processes of `command` running. A process that dies is restarted after
    `backoff_s * 2^(deaths in a row - 1)` (at most `max_backoff_s`); one that ran `healthy_after_s` resets the
    count. `stop` sends SIGTERM (running jobs go back to the queue), then SIGKILL after `timeout`."""

    def __init__(self, command: Sequence[str], env: Mapping[str, str], count: int, backoff_s: float = 1.0,
                 max_backoff_s: float = 60.0, healthy_after_s: float = 60.0, poll_s: float = 0.5):
        self._command, self._env = list(command), dict(env)
        self._backoff_s, self._max_backoff_s, self._healthy_after_s = backoff_s, max_backoff_s, healthy_after_s
        self._poll_s = poll_s
        self._slots = [_Slot() for _ in range(count)]
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._restarts = 0
        self._thread = threading.Thread(target=self._watch, name="bcf-worker-supervisor", daemon=True)

    def start(self) -> None:
        with self._lock:
            for slot in self._slots:
                self._spawn(slot)
        if self._slots:
            self._thread.start()

    def status(self) -> WorkerStatus:
        with self._lock:
            live = sum(slot.process is not None and slot.process.poll() is None for slot in self._slots)
            return WorkerStatus(len(self._slots), live, self._restarts)

    def stop(self, timeout: float = 60.0) -> None:
        self._stopping.set()
        if self._thread.is_alive():
            self._thread.join()
        processes = [slot.process for slot in self._slots if slot.process is not None]
        for process in processes:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for process in processes:
            try:
                process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    def _spawn(self, slot: _Slot) -> None:
        slot.process = subprocess.Popen(self._command, env=self._env)
        slot.started, slot.restart_at = time.monotonic(), None

    def _watch(self) -> None:
        """Reap and replace, every `poll_s`, on the thread that also started the replacements (the kernel's
        parent-death signal follows the thread that forked)."""
        while not self._stopping.wait(self._poll_s):
            now = time.monotonic()
            with self._lock:
                for slot in self._slots:
                    self._tend(slot, now)

    def _tend(self, slot: _Slot, now: float) -> None:
        if slot.restart_at is not None:
            if now >= slot.restart_at:
                self._spawn(slot)
                self._restarts += 1
            return
        code = None if slot.process is None else slot.process.poll()  # poll() also reaps the dead child
        if slot.process is None or code is None:
            return
        slot.failures = 1 if now - slot.started >= self._healthy_after_s else slot.failures + 1
        pause = min(self._max_backoff_s, self._backoff_s * 2 ** (slot.failures - 1))
        slot.restart_at = now + pause
        print(f"bcf serve: worker pid {slot.process.pid} exited with code {code}; starting another in {pause:.0f} s",
              file=sys.stderr, flush=True)
