"""The jobs table in Redis (redis-py), for API replicas and workers on several machines.

Each job is a hash (``<prefix>:job:<id>``, every field JSON-encoded), indexed by sorted sets of
creation time: all jobs and one set per status. Every change runs in an optimistic
``WATCH``/``MULTI`` transaction that retries when another process touched the same keys, so the
lifecycle rules of :mod:`service.jobs.transitions` hold across machines exactly as in SQLite.
Duration statistics are kept as counters updated in the same transaction that finishes a job.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable

import redis

from service.jobs.records import (
    ACTIVE,
    DURATION_BUCKETS,
    STATUSES,
    SUCCEEDED,
    TERMINAL,
    IdempotencyConflict,
    Job,
    JobStats,
    QueueFull,
)
from service.jobs.transitions import TransitionStore

_FIELDS = [f.name for f in dataclasses.fields(Job)]
_RECENT = 20  # finished jobs averaged for the queue's Retry-After estimate


def _encode(job: Job) -> dict[str, str]:
    return {name: json.dumps(getattr(job, name)) for name in _FIELDS}


def _decode(values: dict[bytes, bytes]) -> Job:
    return Job(**{key.decode(): json.loads(value) for key, value in values.items() if key.decode() in _FIELDS})


class RedisJobStore(TransitionStore):
    """The job store in the Redis database at ``url`` under the key prefix ``prefix``."""

    def __init__(self, url: str, prefix: str = "hypnerf"):
        self.redis = redis.Redis.from_url(url)
        self.prefix = prefix
        try:
            self.redis.ping()
        except redis.RedisError as exc:
            where = "{host}:{port}".format(**{"host": "?", "port": "?", **self.redis.connection_pool.connection_kwargs})
            raise ConnectionError(f"cannot reach Redis at {where} (HYPNERF_REDIS_URL): {exc}; start it or fix the URL") from None

    def _key(self, *parts: str) -> str:
        return ":".join((self.prefix, *parts))

    def _job_key(self, job_id: str) -> str:
        return self._key("job", job_id)

    def _status_key(self, status: str) -> str:
        return self._key("status", status)

    # the API side ----------------------------------------------------------------------------
    def create(self, job: Job, *, max_active: int) -> tuple[Job, bool]:
        idem_key = self._key("idempotency")
        active_keys = [self._status_key(s) for s in ACTIVE]

        def attempt(pipe: redis.client.Pipeline) -> tuple[Job, bool]:
            if job.idempotency_key is not None:
                earlier = pipe.hget(idem_key, job.idempotency_key)
                if earlier is not None:
                    existing = self._read(pipe, earlier.decode())
                    if existing is None or existing.request_hash != job.request_hash:
                        raise IdempotencyConflict(earlier.decode())
                    return existing, False
            active = sum(pipe.zcard(key) for key in active_keys)
            if active >= max_active:
                raise QueueFull(active)
            pipe.multi()
            pipe.hset(self._job_key(job.id), mapping=_encode(job))
            pipe.zadd(self._key("jobs"), {job.id: job.created_at})
            pipe.zadd(self._status_key(job.status), {job.id: job.created_at})
            if job.idempotency_key is not None:
                pipe.hset(idem_key, job.idempotency_key, job.id)
            return job, True

        return self.redis.transaction(attempt, idem_key, *active_keys, value_from_callable=True)

    def _read(self, client, job_id: str) -> Job | None:
        values = client.hgetall(self._job_key(job_id))
        return _decode(values) if values else None

    def get(self, job_id: str) -> Job | None:
        return self._read(self.redis, job_id)

    def list(self, *, status: str | None, limit: int, before: tuple[float, str] | None) -> list[Job]:
        index = self._status_key(status) if status is not None else self._key("jobs")
        if before is None:
            members = self.redis.zrevrange(index, 0, limit - 1)
        else:
            # members tied on the cursor's time come in descending id order: skip up to the cursor's id
            ties = len(self.redis.zrangebyscore(index, before[0], before[0]))
            candidates = self.redis.zrevrangebyscore(index, before[0], "-inf", start=0, num=limit + ties)
            members = [m for m in candidates if self.redis.zscore(index, m) < before[0] or m.decode() < before[1]][:limit]
        jobs = [self.get(member.decode()) for member in members]
        return [job for job in jobs if job is not None]

    def count_active(self) -> int:
        return sum(self.redis.zcard(self._status_key(s)) for s in ACTIVE)

    # primitives of the lifecycle ---------------------------------------------------------------
    def _change(self, job_id: str, change: Callable[[Job], bool]) -> tuple[Job | None, bool]:
        key = self._job_key(job_id)

        def attempt(pipe: redis.client.Pipeline) -> tuple[Job | None, bool]:
            job = self._read(pipe, job_id)
            if job is None:
                return None, False
            before = job.status
            if not change(job):
                return job, False
            pipe.multi()
            pipe.hset(key, mapping=_encode(job))
            if job.status != before:
                pipe.zrem(self._status_key(before), job_id)
                pipe.zadd(self._status_key(job.status), {job_id: job.created_at})
                if job.status in TERMINAL and job.started_at is not None:
                    self._count_duration(pipe, job)
            return job, True

        return self.redis.transaction(attempt, key, value_from_callable=True)

    def _count_duration(self, pipe: redis.client.Pipeline, job: Job) -> None:
        duration = job.finished_at - job.started_at
        stats = self._key("durations")
        for bound in DURATION_BUCKETS:
            if duration <= bound:
                pipe.hincrby(stats, f"le:{bound!r}", 1)
        pipe.hincrby(stats, "count", 1)
        pipe.hincrbyfloat(stats, "sum", duration)
        if job.status == SUCCEEDED:
            pipe.lpush(self._key("recent"), duration)
            pipe.ltrim(self._key("recent"), 0, _RECENT - 1)

    def running_ids(self) -> list[str]:
        return [m.decode() for m in self.redis.zrange(self._status_key("running"), 0, -1)]

    def queued_ids(self) -> list[str]:
        return [m.decode() for m in self.redis.zrange(self._status_key("queued"), 0, -1)]

    def stats(self) -> JobStats:
        by_status = {status: self.redis.zcard(self._status_key(status)) for status in STATUSES}
        counters = {k.decode(): v for k, v in self.redis.hgetall(self._key("durations")).items()}
        buckets = [int(counters.get(f"le:{bound!r}", 0)) for bound in DURATION_BUCKETS] + [int(counters.get("count", 0))]
        recent = [float(v) for v in self.redis.lrange(self._key("recent"), 0, -1)]
        return JobStats({k: v for k, v in by_status.items() if v}, buckets, float(counters.get("sum", 0.0)),
                        sum(recent) / len(recent) if recent else None)

    def close(self) -> None:
        self.redis.close()
