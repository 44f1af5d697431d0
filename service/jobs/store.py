"""The jobs table in SQLite (stdlib ``sqlite3``, WAL mode): the source of truth on one machine.

WAL lets the API process read while a worker process writes; every state change is one
conditional ``UPDATE`` (or an ``IMMEDIATE`` transaction where it reads first), so concurrent API
and worker processes never interleave half-changes. Connections are per thread and per process
(a forked worker never reuses its parent's connection).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sqlite3
import threading
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

from service.jobs.records import (
    ACTIVE,
    DURATION_BUCKETS,
    JSON_FIELDS,
    QUEUED,
    RUNNING,
    SUCCEEDED,
    TERMINAL,
    IdempotencyConflict,
    Job,
    JobStats,
    QueueFull,
)
from service.jobs.transitions import TransitionStore

_COLUMNS = [f.name for f in dataclasses.fields(Job)]
_SCHEMA = """
create table if not exists jobs (
    id text primary key,
    kind text not null,
    status text not null,
    idempotency_key text unique,
    request_hash text not null,
    request text not null,
    created_at real not null,
    updated_at real not null,
    queued_at real not null,
    started_at real,
    finished_at real,
    attempts integer not null default 0,
    max_attempts integer not null,
    lease_owner text,
    lease_expires real,
    heartbeat_at real,
    cancel_requested integer not null default 0,
    progress text,
    result text,
    error text,
    webhook text
);
create index if not exists jobs_status_created on jobs (status, created_at);
create index if not exists jobs_created on jobs (created_at, id);
"""
_RECENT = 20  # finished jobs averaged for the queue's Retry-After estimate


def _row_to_job(row: sqlite3.Row) -> Job:
    values = dict(row)
    for name in JSON_FIELDS:
        values[name] = json.loads(values[name]) if values[name] is not None else None
    values["cancel_requested"] = bool(values["cancel_requested"])
    return Job(**{name: values[name] for name in _COLUMNS})


def _job_to_row(job: Job) -> dict:
    values = dataclasses.asdict(job)
    for name in JSON_FIELDS:
        values[name] = json.dumps(values[name]) if values[name] is not None else None
    values["cancel_requested"] = int(values["cancel_requested"])
    return values


class SqliteJobStore(TransitionStore):
    """The job store on one SQLite file (``<state_dir>/jobs/jobs.db``)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        with self._connection() as conn:
            conn.execute("pragma journal_mode=wal")
            conn.executescript(_SCHEMA)

    def _connection(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None or self._local.pid != os.getpid():
            conn = sqlite3.connect(self.path, timeout=10.0, isolation_level=None)
            conn.row_factory = sqlite3.Row
            conn.execute("pragma busy_timeout=10000")
            conn.execute("pragma synchronous=normal")
            self._local.conn, self._local.pid = conn, os.getpid()
        return conn

    @contextmanager
    def _transaction(self):
        conn = self._connection()
        conn.execute("begin immediate")
        try:
            yield conn
        except BaseException:
            conn.execute("rollback")
            raise
        conn.execute("commit")

    # the API side ----------------------------------------------------------------------------
    def create(self, job: Job, *, max_active: int) -> tuple[Job, bool]:
        with self._transaction() as conn:
            if job.idempotency_key is not None:
                row = conn.execute("select * from jobs where idempotency_key = ?", (job.idempotency_key,)).fetchone()
                if row is not None:
                    if row["request_hash"] != job.request_hash:
                        raise IdempotencyConflict(row["id"])
                    return _row_to_job(row), False
            active = conn.execute(f"select count(*) from jobs where status in {ACTIVE}").fetchone()[0]
            if active >= max_active:
                raise QueueFull(active)
            values = _job_to_row(job)
            conn.execute(f"insert into jobs ({', '.join(values)}) values ({', '.join('?' * len(values))})", tuple(values.values()))
        return job, True

    def get(self, job_id: str) -> Job | None:
        row = self._connection().execute("select * from jobs where id = ?", (job_id,)).fetchone()
        return _row_to_job(row) if row is not None else None

    def list(self, *, status: str | None, limit: int, before: tuple[float, str] | None) -> list[Job]:
        where, params = [], []
        if status is not None:
            where.append("status = ?")
            params.append(status)
        if before is not None:
            where.append("(created_at < ? or (created_at = ? and id < ?))")
            params += [before[0], before[0], before[1]]
        sql = "select * from jobs" + (" where " + " and ".join(where) if where else "")
        rows = self._connection().execute(sql + " order by created_at desc, id desc limit ?", (*params, limit)).fetchall()
        return [_row_to_job(row) for row in rows]

    def count_active(self) -> int:
        return self._connection().execute(f"select count(*) from jobs where status in {ACTIVE}").fetchone()[0]

    # primitives of the lifecycle ---------------------------------------------------------------
    def _change(self, job_id: str, change: Callable[[Job], bool]) -> tuple[Job | None, bool]:
        with self._transaction() as conn:
            row = conn.execute("select * from jobs where id = ?", (job_id,)).fetchone()
            if row is None:
                return None, False
            job = _row_to_job(row)
            if not change(job):
                return job, False
            values = _job_to_row(job)
            del values["id"]
            conn.execute(f"update jobs set {', '.join(f'{name} = ?' for name in values)} where id = ?",
                         (*values.values(), job_id))
        return job, True

    def running_ids(self) -> list[str]:
        return self._ids(RUNNING)

    def queued_ids(self) -> list[str]:
        return self._ids(QUEUED)

    def _ids(self, status: str) -> list[str]:
        return [row[0] for row in self._connection().execute("select id from jobs where status = ?", (status,))]

    def stats(self) -> JobStats:
        conn = self._connection()
        by_status = {row[0]: row[1] for row in conn.execute("select status, count(*) from jobs group by status")}
        cases = ", ".join(f"sum(case when finished_at - started_at <= {bound!r} then 1 else 0 end)" for bound in DURATION_BUCKETS)
        row = conn.execute(f"select {cases}, count(*), sum(finished_at - started_at) from jobs "
                           f"where status in {TERMINAL} and started_at is not null").fetchone()
        recent = conn.execute("select avg(d) from (select finished_at - started_at as d from jobs where status = ? "
                              "order by finished_at desc limit ?)", (SUCCEEDED, _RECENT)).fetchone()[0]
        buckets = [int(v or 0) for v in row[:len(DURATION_BUCKETS)]] + [int(row[len(DURATION_BUCKETS)])]
        return JobStats(by_status, buckets, float(row[-1] or 0.0), recent)

    def close(self) -> None:
        conn = getattr(self._local, "conn", None)
        if conn is not None and self._local.pid == os.getpid():
            conn.close()
        self._local = threading.local()
