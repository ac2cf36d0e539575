"""`bcf serve` and `bcf worker`: the HTTP service and the job workers (thin layer over bcf.service / bcf.jobs).

Settings come from the environment or a .env file (`bcf.jobs.settings.Settings`), not from flags.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import signal
import sys
from typing import TYPE_CHECKING, Annotated, Optional

from cyclopts.types import NonNegativeInt, PositiveInt

from bcf.core import CompressOptions, InputError
from bcf.cli import model_flags

if TYPE_CHECKING:
    from bcf.jobs.queue import JobQueue

SETTINGS = ("Settings come from the environment or a .env file: BCF_DATA_DIR, BCF_API_TOKENS, BCF_QUEUE_URL, "
            "BCF_MAX_UPLOAD_MB and more (see the README).")
# The workers' device: the `device` field of the compression options (choices and default from the model).
Device = Annotated[CompressOptions, model_flags("device")]


def _settings():
    from pydantic import ValidationError

    from bcf.jobs.settings import Settings

    try:
        return Settings()
    except ValidationError as exc:  # named by their environment variables, not by flags
        problems = "; ".join(f"BCF_{'.'.join(map(str, e['loc'])).upper()}: {e['msg']}" for e in exc.errors())
        raise InputError(f"bad setting: {problems}") from None


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def serve(*, host: str = "127.0.0.1", port: PositiveInt = 8000, workers: Optional[NonNegativeInt] = None,
          options: Device = CompressOptions()) -> int:
    """Run the HTTP API (and, in embedded mode, worker processes): POST materials, GET results.

    {SETTINGS} Without BCF_API_TOKENS the API listens on 127.0.0.1 only.

    Args:
        host: address to listen on
        port: port
        workers: worker processes to start beside the API (default: 1 in embedded mode, 0 with BCF_QUEUE_URL,
            where workers run on their own with 'bcf worker')
        options.device: device of those workers
    """
    import uvicorn

    from bcf.core import require_device
    from bcf.jobs.supervisor import WorkerSupervisor
    from bcf.service.app import create_app, gated

    settings = _settings()
    if not settings.token_tenants() and not _is_loopback(host):
        print(f"bcf serve: no BCF_API_TOKENS configured: listening on 127.0.0.1 only, not {host} "
              "(set BCF_API_TOKENS to accept other hosts)", file=sys.stderr, flush=True)
        host = "127.0.0.1"
    require_device(options.device)
    count = workers if workers is not None else (0 if settings.farm_mode else 1)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "BCF_DATA_DIR": str(settings.data_dir)}
    supervisor = WorkerSupervisor([sys.executable, "-m", "bcf", "worker", "--device", options.device,
                                   "--exit-with-parent", str(os.getpid())], env, count)
    api = create_app(settings, supervisor.status if count else None)
    _rebuild_records(api.state.queue)
    app = gated(api, settings)
    supervisor.start()
    mode = f"farm mode, queue {settings.queue_url}" if settings.farm_mode else "embedded mode"
    print(f"bcf serve: {mode}, data in {settings.data_dir}, {count} worker process(es), "
          f"API on http://{host}:{port} (docs at /docs)", file=sys.stderr, flush=True)
    # uvicorn shuts down gracefully on SIGTERM / SIGINT and then re-raises the signal; these handlers turn that
    # into a normal return so the workers below are stopped too, and SIGTERM ends with exit code 0.
    signal.signal(signal.SIGTERM, _stop_serving)
    signal.signal(signal.SIGINT, _stop_serving)
    try:
        uvicorn.run(app, host=host, port=port, log_level="info")
    except _StopServing:
        pass
    finally:
        supervisor.stop(timeout=60)  # SIGTERM: running jobs go back to the queue
    return 0


def _rebuild_records(queue: "JobQueue") -> None:
    """Records the store lost while the service was down, back from the data folder before the API answers
    (`bcf.jobs.recovery`); a store that does not answer yet is left to the workers' recovery passes."""
    from bcf.jobs.store import StoreUnavailable

    try:
        report = queue.rebuild_if_needed()
    except StoreUnavailable as exc:
        print(f"bcf serve: job records not checked: {exc}", file=sys.stderr, flush=True)
        return
    if report is not None and report.changed():
        print("bcf serve: job records rebuilt from the data folder: " + "; ".join(report.lines()), file=sys.stderr,
              flush=True)


class _StopServing(Exception):
    pass


def _stop_serving(signum: int, frame: object) -> None:
    raise _StopServing()


def worker(*, options: Device = CompressOptions(), concurrency: PositiveInt = 1,
           exit_with_parent: Optional[PositiveInt] = None) -> int:
    """Run compression jobs from the queue (embedded SQLite queue, or Redis with BCF_QUEUE_URL).

    {SETTINGS} SIGTERM or Ctrl-C puts running jobs back in the queue.

    Args:
        options.device: torch device for training
        concurrency: jobs run at the same time (default: 1, one per GPU)
        exit_with_parent: end (as on SIGTERM) when the process that started this one ends; 'bcf serve' passes
            its PID
    """
    if exit_with_parent is not None:
        from bcf.jobs.supervisor import exit_with_parent as arrange_exit

        arrange_exit(exit_with_parent)
    from bcf.core import require_device
    from bcf.jobs.worker import Worker

    settings = _settings()
    require_device(options.device)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s bcf-worker %(levelname)s "
                        "%(message)s", datefmt="%Y-%m-%d %H:%M:%S")
    Worker(settings, options.device).serve(concurrency)
    return 0


for _command in (serve, worker):  # one text for both: where their settings come from
    _command.__doc__ = _command.__doc__.replace("{SETTINGS}", SETTINGS)
COMMANDS = (serve, worker)
