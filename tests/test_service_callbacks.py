"""Job completion callbacks: a real receiver (an HTTP server in the test process on 127.0.0.1) gets the job
object, signed with BCF_CALLBACK_SECRET, when a job ends; a receiver that fails is tried again."""

from __future__ import annotations

import hashlib
import hmac
import json
import threading
from datetime import datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Iterator

import pytest

from service_harness import TINY_OPTIONS, BcfEnvironment, Server, tiny_material, wait_until

SECRET = "callback-secret-for-tests"


class Receiver:
    """An HTTP server that records every POST (headers and body) and answers 500 to the first `failures`."""

    def __init__(self, failures: int = 0):
        self.requests: list[tuple[dict[str, str], bytes]] = []
        self.failures = failures
        self.hold = False  # True: answer nothing until `released` is set (a receiver that hangs)
        self.released = threading.Event()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 (the http.server name)
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                receiver.requests.append(({k.lower(): v for k, v in self.headers.items()}, body))
                if receiver.hold:
                    receiver.released.wait(60)
                self.send_response(500 if len(receiver.requests) <= receiver.failures else 200)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/bcf-done"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.released.set()
        self.server.shutdown()
        self.server.server_close()


def _signed(headers: dict[str, str], body: bytes) -> bool:
    expected = "sha256=" + hmac.new(SECRET.encode(), body, hashlib.sha256).hexdigest()
    return hmac.compare_digest(headers.get("x-bcf-signature", ""), expected)


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    receiver = Receiver()
    yield receiver
    receiver.close()


def _submit(server: Server, variant: int, callback_url: str) -> dict[str, Any]:
    response = server.client.post("/v1/jobs", files=tiny_material(variant),
                                  data={"options": json.dumps(TINY_OPTIONS), "callback_url": callback_url})
    assert response.status_code == 202, response.text
    return response.json()


def test_a_finished_job_is_posted_to_its_callback_url_signed(tmp_path: Path, receiver: Receiver) -> None:
    receiver.failures = 2  # 500, 500, then 200: the worker tries again with backoff
    environment = BcfEnvironment(tmp_path, callback_secret=SECRET, callback_attempts=4)
    server = environment.serve(workers=1)
    try:
        job = _submit(server, 60, receiver.url)
        assert server.stored(job["id"]).callback_url == receiver.url and "callback_url" not in job
        done = server.wait_finished(job["id"], timeout=180)
        assert done["state"] == "succeeded", done["error"]
        wait_until(lambda: len(receiver.requests) >= 3, 30, "three callback attempts", logs=(server.log,))
    finally:
        server.stop()
    assert len(receiver.requests) == 3  # the third got 200: no more
    for headers, body in receiver.requests:
        assert _signed(headers, body) and headers["x-bcf-job"] == job["id"]
        posted = json.loads(body)
        assert posted["id"] == job["id"] and posted["state"] == "succeeded"
        assert posted["result"]["psnr"] == done["result"]["psnr"]
        assert "tenant" not in posted and "input_key" not in posted  # the public job object only


def test_a_receiver_that_hangs_does_not_hold_up_the_worker(tmp_path: Path, receiver: Receiver) -> None:
    receiver.hold = True
    server = BcfEnvironment(tmp_path, callback_secret=SECRET).serve(workers=1)  # one worker: jobs one by one
    try:
        first = _submit(server, 63, receiver.url)
        second = server.client.post("/v1/jobs", files=tiny_material(64), data={"options": json.dumps(TINY_OPTIONS)})
        done = server.wait_finished(first["id"], timeout=180)
        assert done["state"] == "succeeded"
        wait_until(lambda: receiver.requests, 30, "the callback request", logs=(server.log,))
        after = server.wait_finished(second.json()["id"], timeout=180)
        assert after["state"] == "succeeded"
    finally:
        server.stop()
    # The worker started the next job at once, while the first job's callback still waited for its answer: a
    # worker that waited for it would have started only after its first POST timed out (10 s), and retried.
    gap = datetime.fromisoformat(after["started_at"]) - datetime.fromisoformat(done["finished_at"])
    assert gap.total_seconds() < 5, gap
    assert gap.total_seconds() > 0  # it did run after the first
    assert receiver.requests[0][0]["x-bcf-job"] == first["id"]


def test_a_cancelled_queued_job_is_posted_too(tmp_path: Path, receiver: Receiver) -> None:
    environment = BcfEnvironment(tmp_path, callback_secret=SECRET)
    server = environment.serve(workers=0)  # nothing runs the job: it is cancelled while queued, by the API
    try:
        job = _submit(server, 61, receiver.url)
        assert server.client.delete(f"/v1/jobs/{job['id']}").json()["state"] == "cancelled"
        wait_until(lambda: receiver.requests, 30, "the callback", logs=(server.log,))
    finally:
        server.stop()
    [(headers, body)] = receiver.requests
    assert _signed(headers, body) and json.loads(body)["state"] == "cancelled"


def test_a_callback_url_that_is_not_http_is_refused(tmp_path: Path) -> None:
    server = BcfEnvironment(tmp_path).serve(workers=0)
    try:
        for url in ("ftp://example.com/x", "not a url", "/relative"):
            response = server.client.post("/v1/jobs", files=tiny_material(62), data={"callback_url": url})
            assert response.status_code == 422 and "callback_url" in response.json()["detail"], response.text
    finally:
        server.stop()
