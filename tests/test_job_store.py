"""The job stores (SQLite file, real Redis) behave the same, `JobQueue` recovers jobs whose worker died, and
`bcf.jobs.submission` makes jobs from staged files without any HTTP.

Every store test runs against both stores: the API and workers rely on `add`'s de-duplication and on `update`
being an atomic read-modify-write, whichever store a deployment uses."""

from __future__ import annotations

import datetime
import threading
import uuid
from pathlib import Path
from typing import Any

import pytest
import redis

from bcf.core import InputError, MaterialFiles, load_texture_set
from bcf.core.options import JobOptions
from bcf.jobs.queue import JobQueue
from bcf.jobs.records import JOB_STATES, InputFile, Job, JobState, utc_now
from bcf.jobs.settings import Settings
from bcf.jobs.store import JobStore, RedisJobStore, SqliteJobStore
from bcf.jobs.submission import StagedMaterial, load_job_material, submit_material
from service_harness import CHAINMAIL, CHAINMAIL_ROLES

HOUR_AGO = utc_now() - datetime.timedelta(hours=1)
LONG_AGO = datetime.datetime(2000, 1, 1, tzinfo=datetime.timezone.utc)
QUEUE_DB = 5  # JobQueue uses the default "bcf" key prefix: keep it in a database of its own, flushed per test


@pytest.fixture(params=["sqlite", "redis"])
def store(request: pytest.FixtureRequest, tmp_path: Path, redis_url: str) -> JobStore:
    """A fresh, empty store: a new SQLite file, or a key prefix no other test uses."""
    if request.param == "sqlite":
        return SqliteJobStore(tmp_path / "jobs.db")
    return RedisJobStore(redis_url, prefix=f"t{uuid.uuid4().hex}")


def make_job(key: str | None = None, state: JobState = "queued", created_at: datetime.datetime = HOUR_AGO,
             **fields: Any) -> Job:
    """A job record as the API would build it, with fake inputs; `updated_at` starts at `created_at`."""
    inputs = [InputFile(role="albedo", name="Color.png", stored_as="albedo.png", sha256="0" * 64, bytes=1)]
    return Job(id=uuid.uuid4().hex[:16], name="test", options=JobOptions(), inputs=inputs,
               input_key=key or uuid.uuid4().hex, state=state, created_at=created_at,
               updated_at=fields.pop("updated_at", created_at), **fields)


def set_state(store: JobStore, job: Job, state: JobState) -> Job:
    changed = store.update(job.id, lambda j: j.model_copy(update={"state": state}))
    assert changed is not None and changed.state == state
    return changed


# ----------------------------------------------------------------------------------------------- add / get


@pytest.mark.parametrize("holder_state", ["queued", "running", "succeeded"])
def test_add_returns_the_job_that_holds_the_key(store: JobStore, holder_state: JobState) -> None:
    first = make_job("key-a")
    assert store.add(first) == (first, True)
    set_state(store, first, holder_state)

    again, created = store.add(make_job("key-a"))
    assert not created and again.id == first.id and again.state == holder_state
    assert store.list()[1] == 1
    other = make_job("key-b")
    assert store.add(other) == (other, True)  # a different key is a different job


@pytest.mark.parametrize("holder_state", ["failed", "cancelled"])
def test_add_after_a_failed_or_cancelled_holder_creates_a_new_job(store: JobStore, holder_state: JobState) -> None:
    first = make_job("key-a")
    store.add(first)
    set_state(store, first, holder_state)

    second = make_job("key-a")
    assert store.add(second) == (second, True)
    third, created = store.add(make_job("key-a"))  # the new job holds the key now
    assert not created and third.id == second.id
    jobs, total = store.list()
    assert total == 2 and {j.id for j in jobs} == {first.id, second.id}


def test_get_returns_the_stored_job_or_none(store: JobStore) -> None:
    job = make_job(notes=["a note"], attempts=2)
    store.add(job)
    assert store.get(job.id) == job
    assert store.get("0123456789abcdef") is None


# ------------------------------------------------------------------------------------------------ update


def test_update_applies_the_change_and_stamps_updated_at(store: JobStore) -> None:
    job = make_job(updated_at=LONG_AGO)
    store.add(job)
    before = utc_now()
    changed = store.update(job.id, lambda j: j.model_copy(update={"state": "running", "worker": "w1"}))
    assert changed is not None and changed.state == "running" and changed.worker == "w1"
    assert changed.updated_at >= before and changed.created_at == job.created_at
    assert store.get(job.id) == changed
    assert [j.id for j in store.list({"running"})[0]] == [job.id] and store.list({"queued"})[1] == 0


def test_update_of_a_missing_job_returns_none_without_calling_the_change(store: JobStore) -> None:
    calls: list[Job] = []
    assert store.update("0123456789abcdef", lambda j: calls.append(j)) is None
    assert calls == []


def test_update_leaves_the_job_alone_when_the_change_returns_none(store: JobStore) -> None:
    job = make_job(updated_at=LONG_AGO)
    store.add(job)
    assert store.update(job.id, lambda j: None) == job
    assert store.get(job.id) == job  # updated_at not stamped either


def test_concurrent_updates_are_atomic(store: JobStore) -> None:
    """4 threads x 25 read-modify-writes of `attempts`: a lost update would leave fewer than 100."""
    job = make_job()
    store.add(job)
    start = threading.Barrier(4)
    errors: list[BaseException] = []

    def increment() -> None:
        try:
            start.wait()
            for _ in range(25):
                store.update(job.id, lambda j: j.model_copy(update={"attempts": j.attempts + 1}))
        except BaseException as exc:  # noqa: BLE001 - reported below, a thread cannot fail the test itself
            errors.append(exc)

    threads = [threading.Thread(target=increment) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert errors == [] and not any(t.is_alive() for t in threads)
    stored = store.get(job.id)
    assert stored is not None and stored.attempts == 100


# -------------------------------------------------------------------------------------------- list / counts


def test_list_is_newest_first_filters_by_state_and_paginates(store: JobStore) -> None:
    states: list[JobState] = ["queued", "running", "queued", "failed", "succeeded", "queued", "cancelled"]
    jobs = [make_job(state=state, created_at=HOUR_AGO + datetime.timedelta(seconds=i))
            for i, state in enumerate(states)]
    for job in reversed(jobs):  # insertion order must not matter, only created_at
        store.add(job)
    newest_first = [j.id for j in reversed(jobs)]

    listed, total = store.list()
    assert [j.id for j in listed] == newest_first and total == 7
    assert store.list(set(JOB_STATES))[0] == listed
    page, total = store.list(offset=2, limit=3)
    assert [j.id for j in page] == newest_first[2:5] and total == 7
    assert store.list(offset=6, limit=10)[0] == [listed[-1]] and store.list(offset=7)[0] == []

    wanted = {"queued", "failed"}
    matching = [j.id for j in reversed(jobs) if j.state in wanted]
    filtered, total = store.list(wanted)
    assert [j.id for j in filtered] == matching and total == 4
    page, total = store.list(wanted, offset=1, limit=2)
    assert [j.id for j in page] == matching[1:3] and total == 4
    assert store.list({"running"})[0] == [jobs[1]]


def test_list_of_one_tenant_keeps_to_its_jobs_with_states_and_pages(store: JobStore) -> None:
    owners = ["alice", "bob", "alice", "alice", "bob"]
    jobs = [make_job(state="failed" if i == 2 else "queued", created_at=HOUR_AGO + datetime.timedelta(seconds=i),
                     tenant=owner) for i, owner in enumerate(owners)]
    for job in jobs:
        store.add(job)
    alices = [j.id for j in reversed(jobs) if j.tenant == "alice"]
    listed, total = store.list(tenant="alice")
    assert [j.id for j in listed] == alices and total == 3
    assert [j.id for j in store.list(tenant="alice", offset=1, limit=1)[0]] == alices[1:2]
    assert [j.id for j in store.list({"queued"}, tenant="alice")[0]] == [alices[0], alices[2]]
    assert store.list({"failed"}, tenant="bob") == ([], 0)
    assert store.list(tenant="carol") == ([], 0)
    assert store.list()[1] == 5  # no tenant: every job (the admin's view)


def test_the_state_index_follows_state_changes(store: JobStore) -> None:
    for state in ["queued", "queued", "running", "failed"]:
        store.add(make_job(state=state))
    moved = make_job()
    store.add(moved)
    set_state(store, moved, "cancelled")
    counts = {state: store.list({state})[1] for state in JOB_STATES}
    assert counts == {"queued": 2, "running": 1, "succeeded": 0, "failed": 1, "cancelled": 1}
    assert [j.id for j in store.list({"cancelled"})[0]] == [moved.id]
    store.ping()


# -------------------------------------------------------------------------------------- JobQueue recovery


@pytest.fixture(params=["sqlite", "redis"])
def queue(request: pytest.FixtureRequest, tmp_path: Path, redis_url: str) -> JobQueue:
    """A JobQueue as the API opens it from settings: SQLite files in the data dir, or Redis (database 5,
    emptied first). Jobs go stale after 1 s and get 2 attempts."""
    settings: dict[str, Any] = {"data_dir": tmp_path / "data", "stale_after_s": 1, "max_attempts": 2}
    if request.param == "redis":
        url = redis_url.rsplit("/", 1)[0] + f"/{QUEUE_DB}"
        redis.Redis.from_url(url).flushdb()
        settings["queue_url"] = url
    return JobQueue(Settings(**settings))


def running_job(heartbeat_s_ago: float, **fields: Any) -> Job:
    beat = utc_now() - datetime.timedelta(seconds=heartbeat_s_ago)
    return make_job(state="running", worker="w1", started_at=beat, heartbeat_at=beat, updated_at=beat, **fields)


def test_recover_requeues_a_stale_running_job(queue: JobQueue) -> None:
    stale = running_job(60, attempts=1)
    queue.store.add(stale)
    assert queue.pending_messages() == 0

    changed = queue.recover()
    assert [j.id for j in changed] == [stale.id]
    after = queue.store.get(stale.id)
    assert after is not None and after.state == "queued" and after.attempts == 1 and after.worker is None
    assert after.progress.stage == "queued"
    assert queue.pending_messages() == 1
    assert queue.recover() == [] and queue.pending_messages() == 1  # nothing more to do


def test_recover_fails_a_stale_job_that_used_every_attempt(queue: JobQueue) -> None:
    spent = running_job(60, attempts=2)
    queue.store.add(spent)
    queue.recover()
    after = queue.store.get(spent.id)
    assert after is not None and after.state == "failed" and after.finished_at is not None
    assert after.error is not None and "2 attempts" in after.error and "w1" in after.error
    assert queue.pending_messages() == 0


def test_recover_cancels_a_stale_job_whose_cancel_was_requested(queue: JobQueue) -> None:
    job = running_job(60, attempts=1, cancel_requested=True)
    queue.store.add(job)
    queue.recover()
    after = queue.store.get(job.id)
    assert after is not None and after.state == "cancelled" and after.finished_at is not None
    assert queue.pending_messages() == 0


def test_recover_leaves_a_job_with_a_fresh_heartbeat_alone(queue: JobQueue) -> None:
    alive = running_job(0, attempts=1)
    queue.store.add(alive)
    assert queue.recover() == []
    assert queue.store.get(alive.id) == alive and queue.pending_messages() == 0


def test_recover_resends_the_message_of_a_queued_job_that_has_none(queue: JobQueue) -> None:
    """A queued job older than stale_after_s with no message (the API died between storing and enqueueing)."""
    orphan = make_job()  # created and updated an hour ago
    queue.store.add(orphan)
    assert [j.id for j in queue.recover()] == [orphan.id] and queue.pending_messages() == 1
    assert queue.recover() == [] and queue.pending_messages() == 1  # it has its message now


def test_cancel(queue: JobQueue) -> None:
    queued, running, done = make_job(), running_job(0, attempts=1), make_job(state="succeeded")
    for job in (queued, running, done):
        queue.store.add(job)

    after = queue.cancel(queued.id)
    assert after is not None and after.state == "cancelled" and after.finished_at is not None
    after = queue.cancel(running.id)
    assert after is not None and after.state == "running" and after.cancel_requested
    assert queue.cancel(done.id) == done  # final jobs are returned unchanged
    assert queue.cancel("0123456789abcdef") is None


# -------------------------------------------------------------------------------------- job creation


def staged_chainmail(folder: Path, **replace: bytes) -> StagedMaterial:
    """The Chainmail004 files copied to folder/<role>/<name>, as a submitter stages them; `replace` swaps the
    bytes of a role's file."""
    files = {}
    for role, name in CHAINMAIL_ROLES.items():
        target = folder / role / name
        target.parent.mkdir(parents=True)
        target.write_bytes(replace.get(role, (CHAINMAIL / name).read_bytes()))
        files[role] = target
    return StagedMaterial(files=files, client_names={role: f"sent {name}" for role, name in CHAINMAIL_ROLES.items()})


def test_submit_material_stores_the_inputs_under_their_names_and_queues_once(tmp_path: Path) -> None:
    queue = JobQueue(Settings(_env_file=None, data_dir=tmp_path / "data"))
    job, created = submit_material(queue, staged_chainmail(tmp_path / "first"), JobOptions(preset="fast"))
    assert created and job.state == "queued" and queue.store.get(job.id) == job and queue.pending_messages() == 1
    assert job.name == "Chainmail004_1K_Color" and job.options.normal_convention == "directx"
    assert {(f.role, f.name, f.stored_as) for f in job.inputs} == {
        (role, f"sent {name}", f"{role}/{name}") for role, name in CHAINMAIL_ROLES.items()}
    stored = queue.inputs_path(job.id)
    assert all((stored / role / name).read_bytes() == (CHAINMAIL / name).read_bytes()
               for role, name in CHAINMAIL_ROLES.items())
    assert not list((tmp_path / "first").rglob("*.png")), "the staged files are moved, not copied"
    assert load_job_material(job, stored, queue.settings).source.files == load_texture_set(
        MaterialFiles(**{role: CHAINMAIL / name for role, name in CHAINMAIL_ROLES.items()},
                      normal_convention="directx")).source.files

    again, created = submit_material(queue, staged_chainmail(tmp_path / "second"), JobOptions(preset="fast"))
    assert not created and again.id == job.id and [p.name for p in stored.parent.iterdir()] == [job.id]


def test_submit_material_raises_input_errors_with_fields_and_leaves_nothing(tmp_path: Path) -> None:
    queue = JobQueue(Settings(_env_file=None, data_dir=tmp_path / "data"))
    small = staged_chainmail(tmp_path / "small", albedo=(CHAINMAIL / "Chainmail004_1K_Opacity.png").read_bytes())
    with pytest.raises(InputError) as raised:  # the opacity map has 1 channel: not an albedo
        submit_material(queue, small, JobOptions())
    assert raised.value.role == "albedo" and raised.value.file == small.files["albedo"]
    with pytest.raises(InputError) as raised:
        submit_material(queue, staged_chainmail(tmp_path / "device"), JobOptions(device="cpu"))
    assert raised.value.options == (("device",),) and "device" in raised.value.message()
    assert queue.store.list()[1] == 0 and not (tmp_path / "data" / "inputs").exists()
