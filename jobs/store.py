"""Where job records live, readable by the API and every worker: SQLite (embedded) or Redis (farm mode).

Both stores keep each job as its JSON and offer the same five operations. `update` is an atomic
read-modify-write (an exclusive SQLite transaction; WATCH/MULTI in Redis), which is how state transitions
stay correct with several workers and the API changing the same job: a change function sees the current
record and returns the new one, or None to leave it alone.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import sqlite3
import threading
import uuid
from pathlib import Path
from typing import Callable, Iterator, Optional, Protocol, TypeVar

from bcf.jobs.records import DEFAULT_TENANT, JOB_STATES, Job, utc_now
from bcf.jobs.settings import Settings

__all__ = ["JobStore", "RedisJobStore", "SqliteJobStore", "StoreFull", "StoreUnavailable", "free_disk_bytes",
           "open_store", "sqlite_failure"]

Change = Callable[[Job], Optional[Job]]
# Jobs that hold their input key: a new submission with the same key returns them instead of a new job
# (unless purged: a tombstone has no results to return).
_KEY_HOLDING_STATES = frozenset({"queued", "running", "succeeded"})
_CORRUPT = frozenset({"SQLITE_NOTADB", "SQLITE_CORRUPT"})  # SQLite's words for a file that is not a usable database
_T = TypeVar("_T")
log = logging.getLogger("bcf.jobs")


class StoreUnavailable(RuntimeError):
    """The job store cannot be reached (Redis down, database locked for too long)."""


class StoreFull(StoreUnavailable):
    """The job database cannot grow: its disk is full."""


# SQLite reports a full disk as SQLITE_FULL, or while growing its WAL index as an I/O error: one with less than
# this free on the database's disk is taken for a full disk.
_NEARLY_FULL_BYTES = 1 << 20


def free_disk_bytes(folder: Path) -> int:
    """Free space on the disk of `folder`, or of its nearest existing parent (the data directory is made later)."""
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return shutil.disk_usage(folder).free


def sqlite_failure(exc: sqlite3.OperationalError, path: Path) -> StoreUnavailable:
    """`exc` of the SQLite database `path` as StoreFull when its disk is full, else as StoreUnavailable."""
    code = exc.sqlite_errorcode & 0xFF  # the primary code: extended codes add detail in the high bits
    if code == sqlite3.SQLITE_FULL or (code == sqlite3.SQLITE_IOERR and
                                       free_disk_bytes(path.parent) < _NEARLY_FULL_BYTES):
        return StoreFull(f"database {path}: the disk is full ({exc}); free space on BCF_DATA_DIR's disk")
    return StoreUnavailable(f"job database {path}: {exc}")


class _Lost(Exception):
    """The SQLite file lost its tables (deleted under us) or became unreadable (`corrupt`)."""

    def __init__(self, corrupt: bool):
        super().__init__("corrupt" if corrupt else "no tables")
        self.corrupt = corrupt


class JobStore(Protocol):
    def add(self, job: Job) -> tuple[Job, bool]:
        """Store `job`, unless a queued, running or succeeded job has its input_key: then (that job, False)."""

    def get(self, job_id: str) -> Optional[Job]: ...

    def update(self, job_id: str, change: Change) -> Optional[Job]:
        """Atomically apply `change` to the job; returns the job as stored afterwards, None if there is none."""

    def list(self, states: Optional[set[str]] = None, offset: int = 0,
             limit: Optional[int] = None, tenant: Optional[str] = None) -> tuple[list[Job], int]:
        """(jobs newest first, total matching), of one tenant or (None) of all."""

    def ping(self) -> None:
        """Raise StoreUnavailable if the store cannot be used."""

    def restore(self, job: Job) -> bool:
        """Store a record read back from the data folder as it is, unless a job with its id exists: stored?"""

    def needs_rebuild(self) -> bool:
        """The store has lost its records (deleted, corrupt, flushed) or is new: rebuild them from the data folder
        (`bcf.jobs.recovery`), then `mark_rebuilt`."""

    def mark_rebuilt(self) -> None: ...


def _stamped(job: Job) -> Job:
    return job.model_copy(update={"updated_at": utc_now()})


class SqliteJobStore:
    """One table in `path`; a connection per operation, so any thread or process may use it (WAL mode).

    A lost or unreadable database file never leaves the store unusable: an operation that finds the file
    deleted (a new empty file, "no such table") recreates the schema, and one that finds it corrupt moves it
    aside (`jobs.db.corrupt-<time>`, never deleted) and starts a new one; then `on_recreated` (the queue's
    rebuild from the data folder, `bcf.jobs.recovery`) runs and the operation is tried once more."""

    def __init__(self, path: Path, on_recreated: Optional[Callable[[], object]] = None):
        self.path = Path(path)
        self.on_recreated = on_recreated
        self.moved_aside: list[Path] = []  # unreadable database files this store moved aside
        self._in_hook = threading.local()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._create_schema()
        except _Lost as lost:  # a corrupt file from before this process: the caller rebuilds (needs_rebuild)
            self._recreate(lost.corrupt)

    def _create_schema(self) -> None:
        with self._connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("CREATE TABLE IF NOT EXISTS jobs (id TEXT PRIMARY KEY, input_key TEXT NOT NULL, "
                       "state TEXT NOT NULL, created_at TEXT NOT NULL, data TEXT NOT NULL)")
            db.execute("CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state, created_at)")
            db.execute("CREATE INDEX IF NOT EXISTS jobs_key ON jobs (input_key)")
            # A new or recreated file has no `rebuilt_at`: its records must be rebuilt from the data folder.
            db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")

    @contextlib.contextmanager
    def _connect(self, write: bool = False) -> Iterator[sqlite3.Connection]:
        """A connection; to `write`, in a transaction that commits only if the block succeeds."""
        try:
            db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        except sqlite3.Error as exc:
            raise StoreUnavailable(f"job database {self.path}: {exc}") from exc
        try:
            if write:
                db.execute("BEGIN IMMEDIATE")  # takes the write lock now: no other writer between read and write
            yield db
            if write:
                db.execute("COMMIT")  # not reached on an exception: closing rolls the transaction back
        except sqlite3.OperationalError as exc:
            if str(exc).startswith("no such table"):
                raise _Lost(corrupt=False) from exc  # the file was deleted: a connection made a new, empty one
            raise sqlite_failure(exc, self.path) from exc
        except sqlite3.DatabaseError as exc:
            if getattr(exc, "sqlite_errorname", "") in _CORRUPT:
                raise _Lost(corrupt=True) from exc
            raise
        finally:
            db.close()

    def _run(self, operation: Callable[[sqlite3.Connection], _T], write: bool = False) -> _T:
        """`operation` in a connection; once more after recreating a lost or corrupt database."""
        try:
            with self._connect(write) as db:
                return operation(db)
        except _Lost as lost:
            self._recreate(lost.corrupt)
        if self.on_recreated is not None and not getattr(self._in_hook, "active", False):
            self._in_hook.active = True  # the hook uses this store: a second loss meanwhile must not recurse
            try:
                self.on_recreated()
            except Exception:  # the store still says it needs a rebuild: the workers' next recovery pass does it
                log.exception("rebuilding the job records after recreating %s failed", self.path)
            finally:
                self._in_hook.active = False
        try:
            with self._connect(write) as db:
                return operation(db)
        except _Lost as lost:
            raise StoreUnavailable(f"job database {self.path}: lost again while being recreated") from lost

    def _recreate(self, corrupt: bool) -> None:
        """The schema in a new file; a corrupt file (with its -wal and -shm) moved aside first. One process at a
        time (a lock file), and only if the file is still unreadable: another process may have done it."""
        with open(self.path.with_name(self.path.name + ".lock"), "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if corrupt and self._unreadable():
                stamp = utc_now().strftime("%Y%m%dT%H%M%S.%fZ")
                aside = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
                for suffix in ("", "-wal", "-shm"):
                    with contextlib.suppress(FileNotFoundError):
                        os.replace(f"{self.path}{suffix}", f"{aside}{suffix}")
                self.moved_aside.append(aside)
                log.error("job database %s is unreadable: moved aside to %s; a new one is rebuilt from the data "
                          "folder", self.path, aside.name)
            elif not corrupt:
                log.error("job database %s was lost: recreated; its records are rebuilt from the data folder",
                          self.path)
            try:
                self._create_schema()
            except _Lost as lost:
                raise StoreUnavailable(f"job database {self.path}: cannot be recreated") from lost

    def _unreadable(self) -> bool:
        try:
            with self._connect() as db:
                return db.execute("PRAGMA quick_check").fetchone()[0] != "ok"
        except _Lost as lost:
            return lost.corrupt

    def needs_rebuild(self) -> bool:
        return self._run(lambda db: db.execute("SELECT 1 FROM meta WHERE key = 'rebuilt_at'").fetchone() is None)

    def mark_rebuilt(self) -> None:
        self._run(lambda db: db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('rebuilt_at', ?)",
                                        (utc_now().isoformat(),)), write=True)

    def restore(self, job: Job) -> bool:
        return self._run(lambda db: db.execute(
            "INSERT OR IGNORE INTO jobs (id, input_key, state, created_at, data) VALUES (?, ?, ?, ?, ?)",
            (job.id, job.input_key, job.state, job.created_at.isoformat(), job.model_dump_json())).rowcount == 1,
            write=True)

    def add(self, job: Job) -> tuple[Job, bool]:
        def body(db: sqlite3.Connection) -> tuple[Job, bool]:
            holding = ",".join("?" * len(_KEY_HOLDING_STATES))
            row = db.execute(f"SELECT data FROM jobs WHERE input_key = ? AND state IN ({holding}) "
                             "AND json_extract(data, '$.purged_at') IS NULL ORDER BY created_at DESC LIMIT 1",
                             (job.input_key, *_KEY_HOLDING_STATES)).fetchone()
            if row is not None:
                return Job.model_validate_json(row[0]), False
            db.execute("INSERT INTO jobs (id, input_key, state, created_at, data) VALUES (?, ?, ?, ?, ?)",
                       (job.id, job.input_key, job.state, job.created_at.isoformat(), job.model_dump_json()))
            return job, True

        return self._run(body, write=True)

    def get(self, job_id: str) -> Optional[Job]:
        row = self._run(lambda db: db.execute("SELECT data FROM jobs WHERE id = ?", (job_id,)).fetchone())
        return None if row is None else Job.model_validate_json(row[0])

    def update(self, job_id: str, change: Change) -> Optional[Job]:
        def body(db: sqlite3.Connection) -> Optional[Job]:
            row = db.execute("SELECT data FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                return None
            job = Job.model_validate_json(row[0])
            changed = change(job)
            if changed is None:
                return job
            changed = _stamped(changed)
            db.execute("UPDATE jobs SET state = ?, data = ? WHERE id = ?",
                       (changed.state, changed.model_dump_json(), job_id))
            return changed

        return self._run(body, write=True)

    def list(self, states: Optional[set[str]] = None, offset: int = 0,
             limit: Optional[int] = None, tenant: Optional[str] = None) -> tuple[list[Job], int]:
        wanted = sorted(states) if states else list(JOB_STATES)
        where = f"state IN ({','.join('?' * len(wanted))})"
        if tenant is not None:  # records written before tenants existed belong to the default tenant
            where, wanted = where + f" AND COALESCE(json_extract(data, '$.tenant'), '{DEFAULT_TENANT}') = ?", \
                [*wanted, tenant]

        def body(db: sqlite3.Connection) -> tuple[list[str], int]:
            total = db.execute(f"SELECT COUNT(*) FROM jobs WHERE {where}", wanted).fetchone()[0]
            rows = db.execute(f"SELECT data FROM jobs WHERE {where} ORDER BY created_at DESC, id LIMIT ? OFFSET ?",
                              (*wanted, -1 if limit is None else limit, offset)).fetchall()
            return [r[0] for r in rows], total

        rows, total = self._run(body)
        return [Job.model_validate_json(r) for r in rows], total

    def ping(self) -> None:
        # Reads the table, so a health check also notices (and repairs) a lost database file.
        self._run(lambda db: db.execute("SELECT 1 FROM jobs LIMIT 1").fetchone())


class RedisJobStore:
    """bcf:job:<id> holds the JSON; sorted sets (score = creation time) index all jobs, each state and each
    tenant; bcf:key:<input_key> names the job that holds a key."""

    def __init__(self, url: str, prefix: str = "bcf"):
        import redis

        self._redis_errors = (redis.exceptions.ConnectionError, redis.exceptions.TimeoutError)
        self._watch_error = redis.exceptions.WatchError
        self.client = redis.Redis.from_url(url, socket_timeout=10, socket_connect_timeout=5)
        self.prefix = prefix

    def _name(self, kind: str, of: str) -> str:
        """The Redis key of a job, a state's index or an input key's holder: <prefix>:<kind>:<of>."""
        return f"{self.prefix}:{kind}:{of}"

    @contextlib.contextmanager
    def _errors(self) -> Iterator[None]:
        try:
            yield
        except self._redis_errors as exc:
            raise StoreUnavailable(f"job store (Redis): {exc}") from exc

    def _optimistic(self, watched: list[str], body: Callable[..., object]) -> object:
        """Run body(pipe) under WATCH until no watched key changed meanwhile."""
        with self._errors(), self.client.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(*watched)
                    return body(pipe)
                except self._watch_error:
                    continue

    def _write_new(self, pipe, job: Job) -> None:
        """Queue, in a MULTI, the record of a job new to the store and its entries in every index."""
        score = job.created_at.timestamp()
        pipe.set(self._name("job", job.id), job.model_dump_json())
        pipe.zadd(f"{self.prefix}:jobs", {job.id: score})
        pipe.zadd(self._name("state", job.state), {job.id: score})
        pipe.zadd(self._name("tenant", job.tenant), {job.id: score})

    def add(self, job: Job) -> tuple[Job, bool]:
        def body(pipe) -> tuple[Job, bool]:
            holder = pipe.get(self._name("key", job.input_key))
            if holder is not None:
                raw = pipe.get(self._name("job", holder.decode()))
                if raw is not None:
                    existing = Job.model_validate_json(raw)
                    if existing.state in _KEY_HOLDING_STATES and existing.purged_at is None:
                        pipe.unwatch()
                        return existing, False
            pipe.multi()
            self._write_new(pipe, job)
            pipe.set(self._name("key", job.input_key), job.id)
            pipe.execute()
            return job, True

        # Watching the key's holder is not enough: its state may change (to failed) meanwhile; that only
        # makes us return a job that just failed, which the client sees and may resubmit.
        return self._optimistic([self._name("key", job.input_key)], body)  # type: ignore[return-value]

    def get(self, job_id: str) -> Optional[Job]:
        with self._errors():
            raw = self.client.get(self._name("job", job_id))
        return None if raw is None else Job.model_validate_json(raw)

    def update(self, job_id: str, change: Change) -> Optional[Job]:
        def body(pipe) -> Optional[Job]:
            raw = pipe.get(self._name("job", job_id))
            if raw is None:
                pipe.unwatch()
                return None
            job = Job.model_validate_json(raw)
            changed = change(job)
            if changed is None:
                pipe.unwatch()
                return job
            changed = _stamped(changed)
            pipe.multi()
            pipe.set(self._name("job", job_id), changed.model_dump_json())
            if changed.state != job.state:
                pipe.zrem(self._name("state", job.state), job_id)
                pipe.zadd(self._name("state", changed.state), {job_id: job.created_at.timestamp()})
            pipe.execute()
            return changed

        return self._optimistic([self._name("job", job_id)], body)  # type: ignore[return-value]

    def list(self, states: Optional[set[str]] = None, offset: int = 0,
             limit: Optional[int] = None, tenant: Optional[str] = None) -> tuple[list[Job], int]:
        with self._errors():
            index = f"{self.prefix}:jobs"
            pipe = self.client.pipeline()
            if states and set(states) != set(JOB_STATES):
                # Merge the per-state indexes into a temporary one (kept for a few seconds, then expired).
                keys = [self._name("state", s) for s in sorted(states)]
                index = f"{self.prefix}:tmp:{'+'.join(sorted(states))}"
                pipe.zunionstore(index, keys)
                pipe.expire(index, 5)
            if tenant is not None:  # and keep the tenant's jobs (jobs stored before tenants existed have none)
                mine = f"{self.prefix}:tmp:{uuid.uuid4().hex}"
                pipe.zinterstore(mine, [index, self._name("tenant", tenant)], aggregate="MAX")
                pipe.expire(mine, 5)
                index = mine
            pipe.execute()
            total = self.client.zcard(index)
            stop = -1 if limit is None else offset + limit - 1
            ids = [i.decode() for i in self.client.zrevrange(index, offset, stop)] if limit != 0 else []
            raws = self.client.mget([self._name("job", i) for i in ids]) if ids else []
        return [Job.model_validate_json(r) for r in raws if r is not None], total

    def ping(self) -> None:
        with self._errors():
            self.client.ping()

    def restore(self, job: Job) -> bool:
        def body(pipe) -> bool:
            if pipe.exists(self._name("job", job.id)):
                pipe.unwatch()
                return False
            pipe.multi()
            self._write_new(pipe, job)
            if job.state in _KEY_HOLDING_STATES:  # unless a job submitted since holds the key
                pipe.set(self._name("key", job.input_key), job.id, nx=True)
            pipe.execute()
            return True

        return self._optimistic([self._name("job", job.id)], body)  # type: ignore[return-value]

    def needs_rebuild(self) -> bool:
        # A key that only a rebuild sets: gone after FLUSHDB, a restart without persistence, or a new Redis.
        with self._errors():
            return not self.client.exists(f"{self.prefix}:rebuilt_at")

    def mark_rebuilt(self) -> None:
        with self._errors():
            self.client.set(f"{self.prefix}:rebuilt_at", utc_now().isoformat())


def open_store(settings: Settings, on_recreated: Optional[Callable[[], object]] = None) -> JobStore:
    """Redis when BCF_QUEUE_URL is set, else SQLite in the data directory (which calls `on_recreated` after
    recreating a lost or corrupt database file)."""
    if settings.queue_url:
        return RedisJobStore(settings.queue_url)
    return SqliteJobStore(settings.data_dir / "jobs.db", on_recreated)

