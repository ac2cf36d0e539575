"""`bcf serve` and `bcf worker`: the HTTP service and the job workers (thin layer over bcf.service / bcf.jobs)."""

from __future__ import annotations

import argparse
import functools
import ipaddress
import logging
import os
import signal
import subprocess
import sys
from typing import Callable

COMMANDS = {
    "serve": "run the HTTP API (and, in embedded mode, worker processes): POST materials, GET results",
    "worker": "run compression jobs from the queue (embedded SQLite queue, or Redis with BCF_QUEUE_URL)",
}
SETTINGS_EPILOG = ("Settings come from the environment or a .env file: BCF_DATA_DIR, BCF_API_TOKENS, BCF_QUEUE_URL, "
                   "BCF_MAX_UPLOAD_MB and more (see the README).")


def add_commands(commands: argparse._SubParsersAction, user_error: type[Exception],
                 positive_int: Callable[[str], int], non_negative_int: Callable[[str], int]) -> None:
    p = commands.add_parser("serve", help=COMMANDS["serve"], description=COMMANDS["serve"] + ".",
                            epilog=SETTINGS_EPILOG + " Without BCF_API_TOKENS the API listens on 127.0.0.1 only.")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1)")
    p.add_argument("--port", type=positive_int, default=8000, help="port (default: 8000)")
    p.add_argument("--workers", type=non_negative_int, metavar="N",
                   help="worker processes to start beside the API (default: 1 in embedded mode, 0 with "
                        "BCF_QUEUE_URL, where workers run on their own with 'bcf worker')")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="device of those workers")
    p.set_defaults(handler=functools.partial(_serve, user_error=user_error))

    p = commands.add_parser("worker", help=COMMANDS["worker"], description=COMMANDS["worker"] + ".",
                            epilog=SETTINGS_EPILOG + " SIGTERM or Ctrl-C puts running jobs back in the queue.")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="torch device for training")
    p.add_argument("--concurrency", type=positive_int, default=1, metavar="N",
                   help="jobs run at the same time (default: 1, one per GPU)")
    p.set_defaults(handler=functools.partial(_worker, user_error=user_error))


def _settings(user_error: type[Exception]):
    from pydantic import ValidationError

    from bcf.jobs.settings import Settings

    try:
        return Settings()
    except ValidationError as exc:
        problems = "; ".join(f"BCF_{'.'.join(map(str, e['loc'])).upper()}: {e['msg']}" for e in exc.errors())
        raise user_error(f"bad setting: {problems}") from None


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _log_to_stderr(name: str) -> None:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s {name} %(levelname)s %(message)s", datefmt="%Y-%m-%d %H:%M:%S")


def _serve(args: argparse.Namespace, user_error: type[Exception]) -> int:
    import uvicorn

    from bcf.service.app import create_app, gated

    settings = _settings(user_error)
    host = args.host
    if not settings.api_tokens and not _is_loopback(host):
        print(f"bcf serve: no BCF_API_TOKENS configured: listening on 127.0.0.1 only, not {host} "
              "(set BCF_API_TOKENS to accept other hosts)", file=sys.stderr, flush=True)
        host = "127.0.0.1"
    if args.device == "cuda":
        _require_cuda(user_error)
    count = args.workers if args.workers is not None else (0 if settings.farm_mode else 1)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    app = gated(create_app(settings), settings)
    env = {**os.environ, "BCF_DATA_DIR": str(settings.data_dir)}
    workers = [subprocess.Popen([sys.executable, "-m", "bcf", "worker", "--device", args.device], env=env)
               for _ in range(count)]
    mode = f"farm mode, queue {settings.queue_url}" if settings.farm_mode else "embedded mode"
    print(f"bcf serve: {mode}, data in {settings.data_dir}, {count} worker process(es), "
          f"API on http://{host}:{args.port} (docs at /docs)", file=sys.stderr, flush=True)
    # uvicorn shuts down gracefully on SIGTERM / SIGINT and then re-raises the signal; these handlers turn that
    # into a normal return so the workers below are stopped too, and SIGTERM ends with exit code 0.
    signal.signal(signal.SIGTERM, _stop_serving)
    signal.signal(signal.SIGINT, _stop_serving)
    try:
        uvicorn.run(app, host=host, port=args.port, log_level="info")
    except _StopServing:
        pass
    finally:
        for worker in workers:
            worker.send_signal(signal.SIGTERM)  # running jobs go back to the queue
        for worker in workers:
            try:
                worker.wait(timeout=60)
            except subprocess.TimeoutExpired:
                worker.kill()
    return 0


class _StopServing(Exception):
    pass


def _stop_serving(signum: int, frame: object) -> None:
    raise _StopServing()


def _require_cuda(user_error: type[Exception]) -> None:
    import torch

    if not torch.cuda.is_available():
        raise user_error(f"--device cuda: torch {torch.__version__} sees no CUDA device; use --device cpu")


def _worker(args: argparse.Namespace, user_error: type[Exception]) -> int:
    from bcf.jobs.worker import Worker

    settings = _settings(user_error)
    if args.device == "cuda":
        _require_cuda(user_error)
    _log_to_stderr("bcf-worker")
    Worker(settings, args.device).serve(args.concurrency)
    return 0
