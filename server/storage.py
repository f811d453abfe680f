"""The embedded store: SQLite (WAL) for tokens, assets' metadata and jobs; files on disk for
blobs and artifacts, all under one data directory::

    DATA/service.sqlite3          tokens, assets, jobs, the sha256 of each stored blob and artifact
    DATA/service.lock             held (flock) by the running service: one service per directory
    DATA/blobs/ab/<sha256><ext>   uploaded content, addressed by its sha256 (shared by owners)
    DATA/blobs/ab/<sha256>.d/     an unpacked robot bundle (URDF / MJCF zip)
    DATA/jobs/<job id>/           a finished job's artifacts (appears whole: renamed into place)
    DATA/tmp/                     uploads and job outputs being written (emptied at start)
    DATA/cache/atlas/             built contact atlases, reused by later jobs (safe to delete)
    DATA/logs/<job id>.log        each job process's output

Every write that others may read is atomic: a blob is written under tmp/ and renamed into
place, a job's artifact folder is renamed into place whole, and a job only becomes
``succeeded`` after that. The service process and its job processes open their own
connections (``connect``); WAL lets readers run beside the one writer. Rows come back
typed: :class:`AssetRow`, :class:`JobRow` (its state a :class:`~server.schemas.JobState`).
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import shutil
import sqlite3
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from .schemas import ACTIVE_STATES, Asset, JobCreate, JobState

SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS tokens (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, token_hash TEXT NOT NULL UNIQUE, created REAL NOT NULL,
    admin INTEGER NOT NULL DEFAULT 0);
CREATE TABLE IF NOT EXISTS assets (
    owner TEXT NOT NULL, sha256 TEXT NOT NULL, kind TEXT NOT NULL, name TEXT NOT NULL,
    size INTEGER NOT NULL, path TEXT NOT NULL, info TEXT NOT NULL, created REAL NOT NULL,
    PRIMARY KEY (owner, sha256, kind));
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, state TEXT NOT NULL, request TEXT NOT NULL,
    idempotency_key TEXT, stage TEXT NOT NULL DEFAULT '', progress REAL NOT NULL DEFAULT 0,
    frames_done INTEGER NOT NULL DEFAULT 0, frames_total INTEGER NOT NULL DEFAULT 0,
    timings TEXT NOT NULL DEFAULT '{}', summary TEXT NOT NULL DEFAULT '{}', error TEXT,
    attempts INTEGER NOT NULL DEFAULT 0, pid INTEGER, cancel_requested INTEGER NOT NULL DEFAULT 0,
    created REAL NOT NULL, started REAL, finished REAL, updated REAL NOT NULL);
CREATE UNIQUE INDEX IF NOT EXISTS jobs_idempotency ON jobs (owner, idempotency_key)
    WHERE idempotency_key IS NOT NULL;
CREATE INDEX IF NOT EXISTS jobs_owner ON jobs (owner, created);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state, created);
CREATE TABLE IF NOT EXISTS blobs (path TEXT PRIMARY KEY, sha256 TEXT NOT NULL, size INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS artifacts (
    job_id TEXT NOT NULL, name TEXT NOT NULL, sha256 TEXT NOT NULL, size INTEGER NOT NULL,
    PRIMARY KEY (job_id, name));
"""


class DataDirLocked(RuntimeError):
    """Another running service holds the data directory's lock."""


def lock_data_dir(root):
    """Lock the data directory ``root`` for this process (``fcntl.flock`` on DATA/service.lock,
    held while the returned file stays open; the kernel drops it when the process dies, even by
    kill -9). ``DataDirLocked`` naming the holder's pid when another service holds it. Taken
    before the store is opened, so a second service changes nothing."""
    import fcntl

    root = Path(root).resolve()
    root.mkdir(parents=True, exist_ok=True)
    handle = open(root / "service.lock", "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "unknown"
        handle.close()
        raise DataDirLocked(f"the data directory {root} is in use by another `handretarget serve` (pid {holder}); "
                            "stop it first, or give this one another --data-dir") from None
    handle.truncate(0)
    handle.write(str(os.getpid()))
    handle.flush()
    return handle


def _marks(values) -> str:
    """``?, ?, ...``: one SQL placeholder per value."""
    return ", ".join("?" * len(values))


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def hash_token(token: str) -> str:
    """Tokens are 256-bit random strings, so one sha256 (not a slow password hash) is enough."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class AssetRow:
    """One owner's asset: ``path`` is relative to the data directory; ``info`` what the
    core's reader found in it (see :mod:`server.assets`)."""

    owner: str
    sha256: str
    kind: str
    name: str
    size: int
    path: str
    info: dict
    created: float

    @property
    def id(self) -> str:
        return self.sha256

    def public(self) -> Asset:
        """The asset as the API shows it (no owner, no server path)."""
        return Asset(id=self.sha256, kind=self.kind, name=self.name, size=self.size, created=self.created,
                     info=self.info)

    @classmethod
    def from_row(cls, row) -> "AssetRow":
        return cls(owner=row["owner"], sha256=row["sha256"], kind=row["kind"], name=row["name"], size=row["size"],
                   path=row["path"], info=json.loads(row["info"]), created=row["created"])


@dataclass(frozen=True)
class JobRow:
    """One job as stored. Times are epoch seconds; ``pid`` the job process while running."""

    id: str
    owner: str
    state: JobState
    request: JobCreate
    idempotency_key: str | None
    stage: str
    progress: float
    frames_done: int
    frames_total: int
    timings: dict
    summary: dict
    error: str | None
    attempts: int
    pid: int | None
    cancel_requested: bool
    created: float
    started: float | None
    finished: float | None
    updated: float

    @classmethod
    def from_row(cls, row) -> "JobRow":
        return cls(id=row["id"], owner=row["owner"], state=JobState(row["state"]),
                   request=JobCreate.model_validate_json(row["request"]), idempotency_key=row["idempotency_key"],
                   stage=row["stage"], progress=row["progress"], frames_done=row["frames_done"],
                   frames_total=row["frames_total"], timings=json.loads(row["timings"]),
                   summary=json.loads(row["summary"]), error=row["error"], attempts=row["attempts"], pid=row["pid"],
                   cancel_requested=bool(row["cancel_requested"]), created=row["created"], started=row["started"],
                   finished=row["finished"], updated=row["updated"])


#: The job columns :meth:`Store.update_job` may set.
_UPDATABLE = frozenset(JobRow.__dataclass_fields__) - {"id", "owner", "request", "idempotency_key", "created"}


@dataclass(frozen=True)
class Paths:
    root: Path

    @property
    def database(self) -> Path:
        return self.root / "service.sqlite3"

    @property
    def blobs(self) -> Path:
        return self.root / "blobs"

    @property
    def jobs(self) -> Path:
        return self.root / "jobs"

    @property
    def tmp(self) -> Path:
        return self.root / "tmp"

    @property
    def atlas_cache(self) -> Path:
        """Built contact atlases (the jobs' ``Executor.atlas_cache``); safe to delete."""
        return self.root / "cache" / "atlas"

    def blob(self, sha256: str, ext: str) -> Path:
        return self.blobs / sha256[:2] / f"{sha256}{ext}"

    def job(self, job_id: str) -> Path:
        return self.jobs / job_id


class Store:
    """Tokens, assets and jobs of one data directory. Thread-safe: one connection per call."""

    def __init__(self, root):
        self.paths = Paths(Path(root).resolve())
        for d in (self.paths.root, self.paths.blobs, self.paths.jobs, self.paths.tmp):
            d.mkdir(parents=True, exist_ok=True)
        with self.connect() as db:
            db.executescript(_SCHEMA)
            row = db.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()
            if row is None:
                db.execute("INSERT INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
            if "admin" not in {r["name"] for r in db.execute("PRAGMA table_info(tokens)")}:  # a store from before
                db.execute("ALTER TABLE tokens ADD COLUMN admin INTEGER NOT NULL DEFAULT 0")
            if row is not None and int(row[0]) != SCHEMA_VERSION:
                raise RuntimeError(f"data directory {self.paths.root} has store schema {row[0]}, "
                                   f"this service reads {SCHEMA_VERSION}")

    @contextmanager
    def connect(self):
        db = sqlite3.connect(self.paths.database, timeout=30.0, isolation_level=None)
        db.row_factory = sqlite3.Row
        try:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")
            db.execute("PRAGMA busy_timeout=30000")
            yield db
        finally:
            db.close()

    def lock(self):
        """:func:`lock_data_dir` of this store's directory."""
        return lock_data_dir(self.paths.root)

    # ---- tokens ------------------------------------------------------------------------------
    def create_token(self, owner: str, admin: bool = False) -> str:
        """A new bearer token for ``owner``; only its hash is stored, so it is shown once. An
        ``admin`` token may also read ``/metrics`` (service-wide numbers)."""
        token = "hr_" + secrets.token_urlsafe(32)
        with self.connect() as db:
            db.execute("INSERT INTO tokens (id, owner, token_hash, created, admin) VALUES (?, ?, ?, ?, ?)",
                       (uuid.uuid4().hex, owner, hash_token(token), time.time(), int(admin)))
        return token

    def token_holder(self, token: str) -> tuple[str, bool] | None:
        """(owner, admin) of a valid token, or None."""
        with self.connect() as db:
            row = db.execute("SELECT owner, admin FROM tokens WHERE token_hash = ?", (hash_token(token),)).fetchone()
        return None if row is None else (row["owner"], bool(row["admin"]))

    def owner_of(self, token: str) -> str | None:
        holder = self.token_holder(token)
        return None if holder is None else holder[0]

    def revoke_tokens(self, owner: str) -> int:
        """Remove every token of ``owner`` (their next request gets 401); how many there were.
        The owner's assets and jobs stay (a new token for the same name reaches them)."""
        with self.connect() as db:
            return db.execute("DELETE FROM tokens WHERE owner = ?", (owner,)).rowcount

    def ping(self) -> None:
        """Raise unless the database answers."""
        with self.connect() as db:
            db.execute("SELECT 1 FROM meta LIMIT 1").fetchone()

    # ---- blobs and assets ----------------------------------------------------------------------
    def new_tmp(self, suffix: str = "") -> Path:
        return self.paths.tmp / f"{uuid.uuid4().hex}{suffix}"

    def put_blob(self, tmp: Path, sha256: str, ext: str) -> Path:
        """Move the finished upload ``tmp`` to its content address and record the stored
        file's sha256 (for a converted rig it is not the upload's). An intact file already
        there is kept; a missing or damaged one is replaced (re-uploading repairs it)."""
        final = self.paths.blob(sha256, ext)
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists() and self.blob_problem(final) is None:
            tmp.unlink(missing_ok=True) if tmp.is_file() else shutil.rmtree(tmp, ignore_errors=True)
            return final
        if final.is_dir():
            shutil.rmtree(final, ignore_errors=True)
        digest, size = (file_sha256(tmp), tmp.stat().st_size) if tmp.is_file() else (None, 0)
        os.replace(tmp, final)
        if digest is not None:
            with self.connect() as db:
                db.execute("INSERT OR REPLACE INTO blobs VALUES (?, ?, ?)", (self._rel(final), digest, size))
        return final

    def _rel(self, path: Path) -> str:
        return str(Path(path).relative_to(self.paths.root))

    def blob_problem(self, path: Path) -> str | None:
        """None when the stored file at ``path`` is whole: it exists and matches the sha256
        recorded when it was stored (a file stored before records existed is recorded now).
        Otherwise what is wrong with it: "missing" or "damaged"."""
        return self._check(path, "SELECT sha256, size FROM blobs WHERE path = ?", (self._rel(path),),
                           "INSERT OR REPLACE INTO blobs VALUES (?, ?, ?)", (self._rel(path),))

    def artifact_problem(self, job_id: str, name: str) -> str | None:
        """As :meth:`blob_problem`, for artifact ``name`` of job ``job_id``."""
        return self._check(self.paths.job(job_id) / name,
                           "SELECT sha256, size FROM artifacts WHERE job_id = ? AND name = ?", (job_id, name),
                           "INSERT OR REPLACE INTO artifacts (job_id, name, sha256, size) VALUES (?, ?, ?, ?)",
                           (job_id, name))

    def _check(self, path: Path, select: str, key: tuple, insert: str, insert_key: tuple) -> str | None:
        if path.is_dir():
            return None  # an unpacked folder: not recorded file by file
        if not path.is_file():
            return "missing"
        with self.connect() as db:
            row = db.execute(select, key).fetchone()
        if row is None:  # stored before hashes were recorded: trust it from now on
            with self.connect() as db:
                db.execute(insert, (*insert_key, file_sha256(path), path.stat().st_size))
            return None
        if path.stat().st_size != row["size"] or file_sha256(path) != row["sha256"]:
            return "damaged"
        return None

    def add_asset(self, owner: str, sha256: str, kind: str, name: str, size: int, path: Path,
                  info: dict) -> tuple[AssetRow, bool]:
        """Record an asset for ``owner``; (asset, created) — an identical earlier upload is kept."""
        rel = str(path.relative_to(self.paths.root))
        with self.connect() as db:
            cur = db.execute("INSERT OR IGNORE INTO assets VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                             (owner, sha256, kind, name, size, rel, json.dumps(info), time.time()))
            created = cur.rowcount == 1
        return self.asset(owner, sha256, kind), created

    def asset(self, owner: str, sha256: str, kind: str | None = None) -> AssetRow | None:
        q = "SELECT * FROM assets WHERE owner = ? AND sha256 = ?" + (" AND kind = ?" if kind else "")
        with self.connect() as db:
            row = db.execute(q, (owner, sha256, kind) if kind else (owner, sha256)).fetchone()
        return None if row is None else AssetRow.from_row(row)

    def assets(self, owner: str, kind: str | None = None, limit: int | None = None,
               after: tuple[float, str, str] | None = None) -> list[AssetRow]:
        """The owner's assets oldest first (by created, sha256, kind); ``limit`` of them (None:
        all) after ``after`` = (created, sha256, kind) (the paging cursor of ``GET /v1/assets``)."""
        q, args = "SELECT * FROM assets WHERE owner = ?", [owner]
        if kind:
            q += " AND kind = ?"
            args.append(kind)
        if after is not None:
            q += " AND (created, sha256, kind) > (?, ?, ?)"
            args += list(after)
        q += " ORDER BY created, sha256, kind"
        if limit is not None:
            q += " LIMIT ?"
            args.append(int(limit))
        with self.connect() as db:
            rows = db.execute(q, args).fetchall()
        return [AssetRow.from_row(r) for r in rows]

    def delete_asset(self, owner: str, sha256: str, kind: str | None = None) -> list[AssetRow]:
        """Remove the owner's asset(s) ``sha256`` (of ``kind``, or every kind); the deleted rows.
        ``LookupError`` naming the job while a queued or running job of the owner uses it. The
        stored file goes once no owner's asset refers to it."""
        with self.connect() as db:
            db.execute("BEGIN IMMEDIATE")
            try:
                q = "SELECT * FROM assets WHERE owner = ? AND sha256 = ?" + (" AND kind = ?" if kind else "")
                rows = [AssetRow.from_row(r) for r in
                        db.execute(q, (owner, sha256, kind) if kind else (owner, sha256)).fetchall()]
                for job in db.execute(f"SELECT id, request FROM jobs WHERE owner = ? AND state IN "
                                      f"({_marks(ACTIVE_STATES)})", (owner, *(x.value for x in ACTIVE_STATES))):
                    request = json.loads(job["request"])
                    for row in rows:
                        used = [f for f, k in (("clip", "clip"), ("rig", "rig"), ("annotations", "annotations"),
                                               ("source_rig", "rig")) if request.get(f) == sha256 and k == row.kind]
                        if used:
                            raise LookupError(f"job {job['id']} (queued or running) uses this asset as {used[0]}; "
                                              "cancel it or wait for it to end")
                for row in rows:
                    db.execute("DELETE FROM assets WHERE owner = ? AND sha256 = ? AND kind = ?",
                               (owner, row.sha256, row.kind))
                orphans = [row.path for row in rows
                           if db.execute("SELECT 1 FROM assets WHERE path = ? LIMIT 1", (row.path,)).fetchone() is None]
                for path in orphans:
                    db.execute("DELETE FROM blobs WHERE path = ?", (path,))
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
        for path in orphans:
            target = self.paths.root / path
            shutil.rmtree(target, ignore_errors=True) if target.is_dir() else target.unlink(missing_ok=True)
        return rows

    def usage(self, owner: str) -> int:
        """Bytes the owner stores: their assets (as uploaded) and their jobs' artifacts."""
        with self.connect() as db:
            assets = db.execute("SELECT COALESCE(SUM(size), 0) FROM assets WHERE owner = ?", (owner,)).fetchone()[0]
            artifacts = db.execute("SELECT COALESCE(SUM(a.size), 0) FROM artifacts a JOIN jobs j ON j.id = a.job_id "
                                   "WHERE j.owner = ?", (owner,)).fetchone()[0]
        return int(assets) + int(artifacts)

    def asset_path(self, asset: AssetRow) -> Path:
        return self.paths.root / asset.path

    # ---- jobs --------------------------------------------------------------------------------
    def create_job(self, owner: str, request: JobCreate, idempotency_key: str | None,
                   max_active: int) -> tuple[JobRow, bool]:
        """Queue a job; (job, created). With an ``idempotency_key`` already used by ``owner``
        the earlier job is returned (``ValueError`` if its request differs). ``LookupError``
        when the owner already has ``max_active`` queued or running jobs."""
        body = json.dumps(request.model_dump(mode="json"), sort_keys=True)
        now = time.time()
        with self.connect() as db:
            db.execute("BEGIN IMMEDIATE")  # the limit check and the insert are one step
            try:
                if idempotency_key is not None:
                    row = db.execute("SELECT * FROM jobs WHERE owner = ? AND idempotency_key = ?",
                                     (owner, idempotency_key)).fetchone()
                    if row is not None:
                        db.execute("COMMIT")
                        earlier = JobRow.from_row(row)
                        if earlier.request != request:
                            raise ValueError("this Idempotency-Key was used for a different request")
                        return earlier, False
                active = db.execute(f"SELECT COUNT(*) FROM jobs WHERE owner = ? AND state IN "
                                    f"({_marks(ACTIVE_STATES)})",
                                    (owner, *(s.value for s in ACTIVE_STATES))).fetchone()[0]
                if active >= max_active:
                    db.execute("COMMIT")
                    raise LookupError(f"you already have {active} queued or running jobs (the limit is {max_active})")
                job_id = uuid.uuid4().hex
                db.execute("INSERT INTO jobs (id, owner, state, request, idempotency_key, created, updated) "
                           "VALUES (?, ?, ?, ?, ?, ?, ?)",
                           (job_id, owner, JobState.QUEUED.value, body, idempotency_key, now, now))
                db.execute("COMMIT")
            except sqlite3.Error:
                db.execute("ROLLBACK")
                raise
        return self.job(job_id), True

    def job(self, job_id: str, owner: str | None = None) -> JobRow | None:
        q = "SELECT * FROM jobs WHERE id = ?" + (" AND owner = ?" if owner is not None else "")
        with self.connect() as db:
            row = db.execute(q, (job_id, owner) if owner is not None else (job_id,)).fetchone()
        return None if row is None else JobRow.from_row(row)

    def jobs(self, owner: str | None = None, states: tuple[JobState, ...] | None = None,
             limit: int | None = None, after: tuple[float, str] | None = None) -> list[JobRow]:
        """Jobs oldest first (by ``created``, then id); ``limit`` of them (None: all) after the
        job ``after`` = (created, id) (the paging cursor of ``GET /v1/jobs``)."""
        where, args = [], []
        if owner is not None:
            where.append("owner = ?")
            args.append(owner)
        if states:
            where.append(f"state IN ({_marks(states)})")
            args += [JobState(x).value for x in states]
        if after is not None:
            where.append("(created > ? OR (created = ? AND id > ?))")
            args += [after[0], after[0], after[1]]
        q = "SELECT * FROM jobs" + (" WHERE " + " AND ".join(where) if where else "") + " ORDER BY created, id"
        if limit is not None:
            q += " LIMIT ?"
            args.append(int(limit))
        with self.connect() as db:
            return [JobRow.from_row(r) for r in db.execute(q, args).fetchall()]

    def delete_job(self, owner: str, job_id: str) -> bool:
        """Remove the owner's finished job ``job_id``: its record, artifacts and log. True when
        it was there; ``LookupError`` while it is queued or running."""
        with self.connect() as db:
            db.execute("BEGIN IMMEDIATE")
            row = db.execute("SELECT state FROM jobs WHERE id = ? AND owner = ?", (job_id, owner)).fetchone()
            if row is None or not JobState(row["state"]).final:
                db.execute("COMMIT")
                if row is None:
                    return False
                raise LookupError(f"job {job_id} is {row['state']}; cancel it first")
            db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))
            db.execute("DELETE FROM artifacts WHERE job_id = ?", (job_id,))
            db.execute("COMMIT")
        shutil.rmtree(self.paths.job(job_id), ignore_errors=True)
        (self.paths.root / "logs" / f"{job_id}.log").unlink(missing_ok=True)
        return True

    def state_counts(self) -> dict[str, int]:
        """{state: number of jobs} over every state."""
        with self.connect() as db:
            rows = db.execute("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state").fetchall()
        return {s.value: 0 for s in JobState} | {r["state"]: r["n"] for r in rows}

    def update_job(self, job_id: str, *, only_if_state: tuple[JobState, ...] | None = None, **fields) -> bool:
        """Set ``fields`` (columns of :class:`JobRow`; dicts stored as JSON); with
        ``only_if_state`` only while the job is in one of those states. True when a row changed."""
        if set(fields) - _UPDATABLE:
            raise TypeError(f"not updatable job fields: {', '.join(sorted(set(fields) - _UPDATABLE))}")
        fields["updated"] = time.time()
        for k in ("timings", "summary"):
            if k in fields:
                fields[k] = json.dumps(fields[k])
        if "state" in fields:
            fields["state"] = JobState(fields["state"]).value
        sets = ", ".join(f"{k} = ?" for k in fields)
        q = f"UPDATE jobs SET {sets} WHERE id = ?"
        args = [*fields.values(), job_id]
        if only_if_state:
            q += f" AND state IN ({_marks(only_if_state)})"
            args += [JobState(x).value for x in only_if_state]
        with self.connect() as db:
            return db.execute(q, args).rowcount == 1

    def claim_next_job(self) -> JobRow | None:
        """The next queued job, marked running (attempts + 1), or None. Slots are shared
        round-robin across owners: first the owners with the fewest running jobs, among those
        the owner whose last job started longest ago (never: first), and that owner's oldest
        queued job. So an owner with one job running yields the next free slot to an owner
        with none, however many jobs the first queued before."""
        with self.connect() as db:
            db.execute("BEGIN IMMEDIATE")
            row = db.execute(
                "SELECT q.id FROM jobs q "
                "LEFT JOIN (SELECT owner, SUM(state = :running) AS running, MAX(started) AS last_start "
                "           FROM jobs GROUP BY owner) o ON o.owner = q.owner "
                "WHERE q.state = :queued "
                "ORDER BY COALESCE(o.running, 0), COALESCE(o.last_start, 0), q.created, q.id LIMIT 1",
                {"running": JobState.RUNNING.value, "queued": JobState.QUEUED.value}).fetchone()
            if row is None:
                db.execute("COMMIT")
                return None
            now = time.time()
            db.execute("UPDATE jobs SET state = ?, attempts = attempts + 1, started = ?, updated = ?, "
                       "stage = 'starting', error = NULL WHERE id = ?", (JobState.RUNNING.value, now, now, row["id"]))
            db.execute("COMMIT")
        return self.job(row["id"])

    # ---- artifacts ---------------------------------------------------------------------------
    def publish_artifacts(self, job_id: str, folder: Path) -> Path:
        """Rename a finished output ``folder`` (under tmp/) into place as the job's artifacts
        and record each file's sha256 (checked whenever one is served); an earlier attempt's
        folder is replaced only after the new one is complete."""
        hashes = {p.name: (file_sha256(p), p.stat().st_size) for p in Path(folder).iterdir() if p.is_file()}
        final = self.paths.job(job_id)
        old = None
        if final.exists():
            old = self.new_tmp(".old")
            os.replace(final, old)
        os.replace(folder, final)
        with self.connect() as db:
            db.execute("BEGIN IMMEDIATE")
            db.execute("DELETE FROM artifacts WHERE job_id = ?", (job_id,))
            db.executemany("INSERT INTO artifacts VALUES (?, ?, ?, ?)",
                           [(job_id, name, digest, size) for name, (digest, size) in hashes.items()])
            db.execute("COMMIT")
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return final
