"""The job lifecycle, written once for every store: each transition is a check and a change of one
job, which a store applies atomically through ``_change`` (a SQLite ``IMMEDIATE`` transaction,
a Redis ``WATCH``/``MULTI`` transaction).

Worker transitions (``renew``, ``finish``, ``release``) require the caller to hold the lease:
``status == running`` and ``lease_owner == owner``. That condition is what makes a job succeed
exactly once even when a presumed-dead worker wakes up and tries to finish it.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable

from service.jobs.records import (
    CANCELED,
    FAILED,
    QUEUED,
    RUNNING,
    TERMINAL,
    Job,
    JobStats,
    Renewal,
    lease_lost_failure,
)


def _holds(job: Job, owner: str) -> bool:
    return job.status == RUNNING and job.lease_owner == owner


class TransitionStore(ABC):
    """Base of the job stores: lifecycle transitions on top of three backend primitives."""

    @abstractmethod
    def _change(self, job_id: str, change: Callable[[Job], bool]) -> tuple[Job | None, bool]:
        """Atomically read the job, call ``change(job)`` (which edits it in place and returns whether
        to write it), write it if so; returns ``(job after, written)``; ``(None, False)`` if absent."""

    @abstractmethod
    def running_ids(self) -> list[str]:
        """Ids of the running jobs."""

    @abstractmethod
    def queued_ids(self) -> list[str]:
        """Ids of the queued jobs."""

    @abstractmethod
    def get(self, job_id: str) -> Job | None:
        """The job, or ``None`` when there is none with that id."""

    # the API side ----------------------------------------------------------------------------
    def cancel(self, job_id: str) -> tuple[Job | None, bool]:
        """A queued job becomes canceled at once; a running one is asked to stop (its worker sees
        it at the next renewal and ends it canceled); a finished one stays as it is. Returns the
        job and whether this call changed it."""
        def change(job: Job) -> bool:
            now = time.time()
            if job.status == QUEUED:
                job.status, job.finished_at, job.updated_at = CANCELED, now, now
                return True
            if job.status == RUNNING and not job.cancel_requested:
                job.cancel_requested, job.updated_at = True, now
                return True
            return False
        return self._change(job_id, change)

    # the worker side -------------------------------------------------------------------------
    def claim(self, job_id: str, owner: str, lease_s: float) -> Job | None:
        """Queued -> running under ``owner``'s lease (attempts + 1); ``None`` when the job is not
        queued (canceled meanwhile, or already taken by another worker)."""
        def change(job: Job) -> bool:
            if job.status != QUEUED:
                return False
            now = time.time()
            job.status, job.attempts, job.lease_owner = RUNNING, job.attempts + 1, owner
            job.lease_expires, job.heartbeat_at, job.started_at, job.updated_at = now + lease_s, now, now, now
            job.progress = None
            return True
        job, written = self._change(job_id, change)
        return job if written else None

    def renew(self, job_id: str, owner: str, lease_s: float, progress: dict | None = None) -> Renewal:
        """Extend the lease (and record ``progress``) if ``owner`` still holds it."""
        def change(job: Job) -> bool:
            if not _holds(job, owner):
                return False
            now = time.time()
            job.lease_expires, job.heartbeat_at = now + lease_s, now
            if progress is not None:
                job.progress, job.updated_at = progress, now
            return True
        job, written = self._change(job_id, change)
        return Renewal(written, bool(job and job.cancel_requested))

    def finish(self, job_id: str, owner: str, status: str, *, result: dict | None = None, error: dict | None = None) -> bool:
        """Running -> ``status`` (succeeded, failed or canceled) if ``owner`` still holds the lease."""
        if status not in TERMINAL:
            raise ValueError(f"a job finishes as one of {TERMINAL}, not {status!r}")

        def change(job: Job) -> bool:
            if not _holds(job, owner):
                return False
            now = time.time()
            job.status, job.result, job.error, job.finished_at, job.updated_at = status, result, error, now, now
            job.lease_owner = job.lease_expires = None
            return True
        return self._change(job_id, change)[1]

    def release(self, job_id: str, owner: str) -> bool:
        """Running -> queued: the worker was stopped (not the job at fault); needs the lease."""
        def change(job: Job) -> bool:
            if not _holds(job, owner):
                return False
            now = time.time()
            job.status, job.queued_at, job.updated_at = QUEUED, now, now
            job.lease_owner = job.lease_expires = None
            return True
        return self._change(job_id, change)[1]

    # upkeep ----------------------------------------------------------------------------------
    def expire_leases(self) -> list[Job]:
        """Re-queue running jobs whose lease expired, fail them once they used ``max_attempts``
        starts, or cancel them if that was asked (no worker is left to do it); returns the jobs
        changed, in their new state."""
        def change(job: Job) -> bool:
            now = time.time()
            if job.status != RUNNING or job.lease_expires is None or job.lease_expires >= now:
                return False
            if job.cancel_requested:
                job.status, job.finished_at = CANCELED, now
            elif job.attempts >= job.max_attempts:
                job.status, job.error, job.finished_at = FAILED, lease_lost_failure(job.attempts), now
            else:
                job.status, job.queued_at = QUEUED, now
            job.lease_owner = job.lease_expires = None
            job.updated_at = now
            return True
        changed = []
        for job_id in self.running_ids():
            job, written = self._change(job_id, change)
            if written:
                changed.append(job)
        return changed

    def stale_queued(self, older_than: float) -> list[str]:
        """Ids of jobs queued since before ``older_than`` (their queue message may have been lost)."""
        jobs = (self.get(job_id) for job_id in self.queued_ids())
        return [job.id for job in jobs if job is not None and job.status == QUEUED and job.queued_at < older_than]

    def touch_queued(self, job_id: str) -> None:
        """Mark a queued job as (re-)enqueued now."""
        def change(job: Job) -> bool:
            if job.status != QUEUED:
                return False
            job.queued_at = time.time()
            return True
        self._change(job_id, change)

    def record_webhook(self, job_id: str, outcome: dict) -> None:
        """Merge the webhook delivery ``outcome`` into the job's webhook record."""
        def change(job: Job) -> bool:
            job.webhook = {**(job.webhook or {}), **outcome}
            return True
        self._change(job_id, change)

    # implemented by each backend -------------------------------------------------------------
    @abstractmethod
    def create(self, job: Job, *, max_active: int) -> tuple[Job, bool]:
        """Insert ``job`` unless its idempotency key names an existing job with the same request
        hash (returns that job and ``False``). Raises ``IdempotencyConflict`` when the key was used
        for a different request, ``QueueFull`` when ``max_active`` jobs are queued or running."""

    @abstractmethod
    def list(self, *, status: str | None, limit: int, before: tuple[float, str] | None) -> list[Job]:
        """Newest first; ``before`` = (created_at, id) of the last job of the previous page."""

    @abstractmethod
    def count_active(self) -> int:
        """How many jobs are queued or running."""

    @abstractmethod
    def stats(self) -> JobStats:
        """Counts by status and the duration histogram of finished jobs."""

    @abstractmethod
    def close(self) -> None:
        """Release this process's connections."""
