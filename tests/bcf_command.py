"""How the tests run the installed `bcf` command as a real subprocess."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path


def _bcf_command() -> list[str]:
    """The console script installed beside this interpreter, else one on PATH, else `python -m bcf`."""
    beside = Path(sys.executable).with_name("bcf")
    if beside.is_file():
        return [str(beside)]
    found = shutil.which("bcf")
    return [found] if found else [sys.executable, "-m", "bcf"]


BCF = _bcf_command()

# One torch thread: tiny training batches run faster on one thread than on two, and two test workers with two
# threads each on a 2-core machine slow down many times over. Results do not depend on the thread count.
ONE_THREAD_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def default_sigint() -> None:
    """Popen preexec_fn for tests that press Ctrl-C: a child inherits an ignored SIGINT from a test run that was
    started in the background (POSIX shells ignore SIGINT in asynchronous jobs), and Python then installs no
    KeyboardInterrupt handler. The default disposition at exec lets the command handle Ctrl-C as in a terminal."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run_bcf(*args: object, timeout: float = 180) -> subprocess.CompletedProcess[str]:
    """Run `bcf ARGS...` to completion and return it (exit code, stdout, stderr as text)."""
    return subprocess.run([*BCF, *map(str, args)], capture_output=True, text=True, timeout=timeout,
                          env=ONE_THREAD_ENV)
