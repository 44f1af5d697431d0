"""The job record and the rules every job store follows (SQLite on one machine, Redis across machines).

A job moves ``queued -> running -> succeeded | failed | canceled`` (or ``queued -> canceled``).
A worker holds a *lease* while it runs a job: ``lease_owner`` plus ``lease_expires``, renewed by
its heartbeat. Every write a worker makes is conditional on still holding the lease, so a worker
that lost its lease (it stalled, or it was presumed dead and the job re-queued) can no longer
change the job, and a job reaches ``succeeded`` exactly once. A ``running`` job whose lease
expired is re-queued (``attempts`` counts the starts) until ``max_attempts``, then failed.
"""

from __future__ import annotations

import time
import uuid
from dataclasses import dataclass, field

QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELED = "queued", "running", "succeeded", "failed", "canceled"
STATUSES = (QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELED)
TERMINAL = (SUCCEEDED, FAILED, CANCELED)
ACTIVE = (QUEUED, RUNNING)

# job fields holding JSON documents (the rest are scalars)
JSON_FIELDS = ("progress", "result", "error", "request", "webhook")

# upper bounds (seconds) of the job-duration histogram buckets; the last bucket is +Inf
DURATION_BUCKETS = (1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0)


class IdempotencyConflict(Exception):
    """The idempotency key was used before with a different request; carries the earlier job's id."""

    def __init__(self, job_id: str):
        super().__init__(job_id)
        self.job_id = job_id


class QueueFull(Exception):
    """As many jobs as allowed are queued or running; carries how many."""

    def __init__(self, active: int):
        super().__init__(active)
        self.active = active


@dataclass
class Job:
    """One job as stored. Times are Unix seconds; JSON fields are plain dicts (or ``None``)."""

    id: str
    kind: str
    request: dict
    request_hash: str
    status: str = QUEUED
    idempotency_key: str | None = None
    created_at: float = 0.0
    updated_at: float = 0.0
    queued_at: float = 0.0
    started_at: float | None = None
    finished_at: float | None = None
    attempts: int = 0
    max_attempts: int = 3
    lease_owner: str | None = None
    lease_expires: float | None = None
    heartbeat_at: float | None = None
    cancel_requested: bool = False
    progress: dict | None = None
    result: dict | None = None
    error: dict | None = None
    webhook: dict | None = None

    @classmethod
    def new(cls, kind: str, request: dict, request_hash: str, *, idempotency_key: str | None, max_attempts: int,
            webhook_url: str | None) -> Job:
        now = time.time()
        return cls(id=uuid.uuid4().hex, kind=kind, request=request, request_hash=request_hash,
                   idempotency_key=idempotency_key, created_at=now, updated_at=now, queued_at=now,
                   max_attempts=max_attempts, webhook={"url": webhook_url} if webhook_url else None)

    @property
    def finished(self) -> bool:
        return self.status in TERMINAL


@dataclass(frozen=True)
class Renewal:
    """What a worker learns when it renews its lease: whether it still holds it, whether the job
    was asked to stop."""

    held: bool
    cancel_requested: bool = False


@dataclass
class JobStats:
    """Counts by status and the duration histogram of finished jobs (for Prometheus)."""

    by_status: dict[str, int] = field(default_factory=dict)
    duration_buckets: list[int] = field(default_factory=list)  # cumulative counts per DURATION_BUCKETS, then +Inf
    duration_sum: float = 0.0
    recent_mean_duration: float | None = None


def failure(title: str, detail: str) -> dict:
    """The problem-like error recorded on a failed job."""
    return {"title": title, "detail": detail}


def lease_lost_failure(attempts: int) -> dict:
    return failure("Job interrupted too often",
                   f"the job was started {attempts} times and each time its worker stopped before finishing "
                   "(killed, out of memory or restarted); submit it again, with fewer steps or smaller images if it is large")
