"""Job completion callbacks for farm schedulers: a job submitted with a `callback_url` gets its public job
object POSTed there when it ends (succeeded, failed or cancelled).

Each delivery runs on a daemon thread of its own, so a slow or dead receiver never holds up the worker or the
API; it is tried `BCF_CALLBACK_ATTEMPTS` times with exponential backoff (tenacity; any 2xx answer ends it), then
given up with a log line. With `BCF_CALLBACK_SECRET` the body is signed: `X-Bcf-Signature: sha256=<hex
HMAC-SHA256 of the body>`, so a receiver can tell the callback came from this service and was not altered.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import threading
from typing import Optional

import httpx
from pydantic import HttpUrl, TypeAdapter, ValidationError
from tenacity import RetryCallState, Retrying, retry_if_exception_type, stop_after_attempt, wait_exponential

from bcf.jobs.records import Job, JobView
from bcf.jobs.settings import Settings

__all__ = ["SIGNATURE_HEADER", "CallbackError", "checked_callback_url", "send_callback", "signature"]

SIGNATURE_HEADER = "X-Bcf-Signature"
MAX_URL_LENGTH = 2048
TIMEOUT_S = 10.0
FIRST_PAUSE_S, LONGEST_PAUSE_S = 0.5, 60.0
log = logging.getLogger("bcf.callbacks")
_URL = TypeAdapter(HttpUrl)


class CallbackError(ValueError):
    """A callback URL that cannot be used."""


def checked_callback_url(url: Optional[str]) -> Optional[str]:
    """`url` if it is an absolute http:// or https:// URL (CallbackError otherwise); None or blank: None."""
    if url is None or not url.strip():
        return None
    if len(url) > MAX_URL_LENGTH:
        raise CallbackError(f"callback_url is longer than {MAX_URL_LENGTH} characters")
    try:
        _URL.validate_python(url)
    except ValidationError:
        raise CallbackError(f"callback_url must be an http:// or https:// URL, got {url!r}") from None
    return url


def signature(body: bytes, secret: str) -> str:
    """The X-Bcf-Signature header value of `body`."""
    return "sha256=" + hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()


def send_callback(job: Job, settings: Settings) -> Optional[threading.Thread]:
    """POST the ended job's public object to its callback_url, on a daemon thread (returned; None: no URL)."""
    if job.callback_url is None:
        return None
    body = JobView.model_validate(job.model_dump()).model_dump_json().encode()
    headers = {"Content-Type": "application/json", "X-Bcf-Job": job.id}
    if settings.callback_secret:
        headers[SIGNATURE_HEADER] = signature(body, settings.callback_secret)
    thread = threading.Thread(target=_deliver, args=(job.id, job.callback_url, body, headers,
                                                     settings.callback_attempts),
                              name=f"callback-{job.id}", daemon=True)
    thread.start()
    return thread


class _Refused(Exception):
    """The receiver answered, but not with a 2xx."""


def _post(url: str, body: bytes, headers: dict[str, str]) -> None:
    answer = httpx.post(url, content=body, headers=headers, timeout=TIMEOUT_S)
    if not answer.is_success:
        raise _Refused(f"HTTP {answer.status_code}")


def _deliver(job_id: str, url: str, body: bytes, headers: dict[str, str], attempts: int) -> None:
    def note_retry(state: RetryCallState) -> None:
        log.warning("job %s: callback attempt %d of %d failed (%s); again in %.1f s", job_id, state.attempt_number,
                    attempts, state.outcome.exception() if state.outcome else "", state.upcoming_sleep)

    retrying = Retrying(stop=stop_after_attempt(attempts), reraise=True, before_sleep=note_retry,
                        wait=wait_exponential(multiplier=FIRST_PAUSE_S, max=LONGEST_PAUSE_S),
                        retry=retry_if_exception_type((httpx.HTTPError, _Refused)))
    try:
        retrying(_post, url, body, headers)
    except (httpx.HTTPError, _Refused) as exc:
        log.error("job %s: callback to its callback_url given up after %d attempts (%s: %s)", job_id, attempts,
                  type(exc).__name__, exc)
        return
    log.info("job %s: callback delivered (attempt %d)", job_id, retrying.statistics.get("attempt_number", 1))
