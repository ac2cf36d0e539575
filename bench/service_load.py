"""Load on the HTTP service over loopback: N concurrent submissions to `bcf serve` in embedded mode (or farm
mode with a private redis-server), then every job polled to completion.

Reports POST /v1/jobs latency (p50 / p95 / max: upload, validation of the image headers, hashing, queueing),
GET /v1/jobs/{id} latency while the workers are busy, and the time until every job finished.
Uses the real processes and materials of the test suite (tests/service_harness.py): tiny 64x64 crops, or with
`--material` a real material folder sent whole by every client (each with its own seed, so each is a job of
its own); `--post-only` measures the submissions and cancels the jobs instead of running them.

    OMP_NUM_THREADS=1 .venv/bin/python bench/service_load.py --jobs 50 -o bench/results/service_load.json
    OMP_NUM_THREADS=1 .venv/bin/python bench/service_load.py --jobs 50 --redis -o bench/results/service_load_redis.json
    OMP_NUM_THREADS=1 .venv/bin/python bench/service_load.py --jobs 50 --post-only \
        --material ../shared/materials/wood_peeling_paint_weathered -o bench/results/service_load_2k.json
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

from service_harness import BcfEnvironment, Server, percentile, redis_server, submit_concurrently  # noqa: E402

from bcf.core import MaterialFiles, resolve_material  # noqa: E402

LOAD_OPTIONS = {"preset": "fast", "phase1_iterations": 10, "phase2_iterations": 10, "batch_size": 256}


def _summary(values: list[float]) -> dict[str, float]:
    return {"p50_ms": round(percentile(values, 50) * 1000, 1), "p95_ms": round(percentile(values, 95) * 1000, 1),
            "max_ms": round(max(values) * 1000, 1)}


def _submit_material(server: Server, folder: Path, jobs: int) -> list[tuple[int, str, float]]:
    """POST the material in `folder` (files per role) from `jobs` threads at once, seeds 0..jobs-1."""
    from concurrent.futures import ThreadPoolExecutor

    roles = resolve_material(folder, MaterialFiles()).roles()
    files = {role: (path.name, path.read_bytes(), "application/octet-stream") for role, path in roles.items()}

    def post(seed: int) -> tuple[int, str, float]:
        started = time.perf_counter()
        response = server.client.post("/v1/jobs", files=files,
                                      data={"options": json.dumps({**LOAD_OPTIONS, "seed": seed})})
        elapsed = time.perf_counter() - started
        return response.status_code, response.json().get("id", response.text), elapsed

    with ThreadPoolExecutor(jobs) as pool:
        return list(pool.map(post, range(jobs)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", type=int, default=50)
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: 2)")
    parser.add_argument("--redis", action="store_true", help="farm mode with a private redis-server")
    parser.add_argument("--material", type=Path, help="a material folder every client sends (default: tiny crops)")
    parser.add_argument("--post-only", action="store_true", help="measure the submissions only; cancel the jobs")
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
        workers = [] if args.post_only else [environment.worker() for _ in range(args.workers)]
        try:
            started = time.perf_counter()
            if args.material:
                posts = _submit_material(server, args.material, args.jobs)
            else:
                posts = submit_concurrently(server, list(range(args.jobs)), LOAD_OPTIONS, threads=args.jobs)
            submitted_s = time.perf_counter() - started
            bad = [p for p in posts if p[0] != 202]
            if bad:
                raise SystemExit(f"submissions failed: {bad[:3]}")
            ids = [job_id for _, job_id, _ in posts]
            if args.post_only:
                for job_id in ids:
                    server.client.delete(f"/v1/jobs/{job_id}")
            polls: list[float] = []
            pending = set() if args.post_only else set(ids)
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

    result = {"jobs": args.jobs, "workers": 0 if args.post_only else args.workers,
              "mode": "farm (Redis)" if args.redis else "embedded", "options": LOAD_OPTIONS,
              "material": str(args.material) if args.material else "64x64 crops of Chainmail004",
              "material_bytes": sum(p.stat().st_size for p in args.material.iterdir()) if args.material else None, "post": _summary([s for _, _, s in posts]), "all_submitted_s": round(submitted_s, 2),
              "get_while_busy": _summary(polls) if polls else None, "gets": len(polls),
              "all_finished_s": None if args.post_only else round(finished_s, 2),
              "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, "
                         f"{__import__('os').cpu_count()} cores"}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
