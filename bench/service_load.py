"""Load on the HTTP service over loopback: N concurrent submissions of tiny real materials to `bcf serve` in
embedded mode (or farm mode with a private redis-server), then every job polled to completion.

Reports POST /v1/jobs latency (p50 / p95 / max: upload, validation by decoding the images, queueing),
GET /v1/jobs/{id} latency while the workers are busy, and the time until every job finished.
Uses the real processes and materials of the test suite (tests/service_harness.py).

    OMP_NUM_THREADS=1 .venv/bin/python bench/service_load.py --jobs 50 -o bench/results/service_load.json
    OMP_NUM_THREADS=1 .venv/bin/python bench/service_load.py --jobs 50 --redis -o bench/results/service_load_redis.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from service_harness import BcfEnvironment, percentile, redis_server, submit_concurrently  # noqa: E402

LOAD_OPTIONS = {"preset": "fast", "phase1_iterations": 10, "phase2_iterations": 10, "batch_size": 256}


def _summary(values: list[float]) -> dict[str, float]:
    return {"p50_ms": round(percentile(values, 50) * 1000, 1), "p95_ms": round(percentile(values, 95) * 1000, 1),
            "max_ms": round(max(values) * 1000, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", type=int, default=50)
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: 2)")
    parser.add_argument("--redis", action="store_true", help="farm mode with a private redis-server")
    parser.add_argument("-o", "--output", type=Path, required=True)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        redis = None
        settings = {}
        if args.redis:
            redis, url = redis_server(root)
            settings["queue_url"] = url
        environment = BcfEnvironment(root, **settings)
        server = environment.serve(workers=0)
        workers = [environment.worker() for _ in range(args.workers)]
        try:
            started = time.perf_counter()
            posts = submit_concurrently(server, list(range(args.jobs)), LOAD_OPTIONS, threads=args.jobs)
            submitted_s = time.perf_counter() - started
            bad = [p for p in posts if p[0] != 202]
            if bad:
                raise SystemExit(f"submissions failed: {bad[:3]}")
            ids = [job_id for _, job_id, _ in posts]
            polls: list[float] = []
            pending = set(ids)
            while pending:
                for job_id in list(pending):
                    t0 = time.perf_counter()
                    job = server.job(job_id)
                    polls.append(time.perf_counter() - t0)
                    if job["state"] in ("succeeded", "failed", "cancelled"):
                        if job["state"] != "succeeded":
                            raise SystemExit(f"job {job_id} {job['state']}: {job['error']}")
                        pending.discard(job_id)
                time.sleep(0.2)
            finished_s = time.perf_counter() - started
            listing = server.client.get("/v1/jobs", params={"limit": 1000}).json()
            assert listing["total"] == args.jobs and len({j["id"] for j in listing["jobs"]}) == args.jobs
        finally:
            for worker in workers:
                worker.stop()
            server.stop()
            if redis:
                redis.stop()

    result = {"jobs": args.jobs, "workers": args.workers, "mode": "farm (Redis)" if args.redis else "embedded",
              "options": LOAD_OPTIONS, "post": _summary([s for _, _, s in posts]), "all_submitted_s": round(submitted_s, 2),
              "get_while_busy": _summary(polls), "gets": len(polls), "all_finished_s": round(finished_s, 2),
              "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, "
                         f"{__import__('os').cpu_count()} cores"}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
