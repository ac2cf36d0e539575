"""A bounded load test on loopback: 50 concurrent submissions to an embedded service with two workers."""

from __future__ import annotations

from pathlib import Path

from service_harness import BcfEnvironment, percentile, submit_concurrently

JOBS = 50
# The smallest real job: 10 + 10 iterations of 256 samples on 64x64 (the load is on the queue, not training).
LOAD_OPTIONS = {"preset": "fast", "phase1_iterations": 10, "phase2_iterations": 10, "batch_size": 256}


def test_fifty_concurrent_submissions_all_complete_once(tmp_path: Path) -> None:
    environment = BcfEnvironment(tmp_path)
    server = environment.serve(workers=2)
    try:
        results = submit_concurrently(server, list(range(100, 100 + JOBS)), LOAD_OPTIONS, threads=JOBS)
        assert [status for status, _, _ in results] == [202] * JOBS, results
        ids = [job_id for _, job_id, _ in results]
        assert len(set(ids)) == JOBS  # 50 distinct materials: 50 jobs
        latencies = [seconds for _, _, seconds in results]
        print(f"\nPOST /v1/jobs x {JOBS} concurrent: p50 {percentile(latencies, 50) * 1000:.0f} ms, "
              f"p95 {percentile(latencies, 95) * 1000:.0f} ms")

        # The same materials again, at once: the same jobs come back, none is created twice.
        again = submit_concurrently(server, list(range(100, 110)), LOAD_OPTIONS, threads=10)
        assert [(status, job_id) for status, job_id, _ in again] == [(200, job_id) for job_id in ids[:10]]

        for job_id in ids:
            job = server.wait_finished(job_id, timeout=300)
            assert job["state"] == "succeeded" and server.stored(job_id).attempts == 1, job
        listing = server.client.get("/v1/jobs", params={"limit": 1000}).json()
        assert listing["total"] == JOBS and sorted(j["id"] for j in listing["jobs"]) == sorted(ids)
        assert len(list((environment.data_dir / "artifacts").iterdir())) == JOBS
        # Ended jobs keep no input images, only their record (job.json, for a rebuild of a lost job store).
        assert [sorted(p.name for p in job.iterdir()) for job in (environment.data_dir / "inputs").iterdir()] == [
            ["job.json"]] * JOBS
    finally:
        server.stop()
