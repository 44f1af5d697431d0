"""The job system of one API process: the store, the queue, the upkeep thread and (optionally)
the embedded worker processes.

The upkeep thread keeps the promises of the lease design: every few seconds it re-queues jobs
whose worker's lease expired (or fails them after ``job_max_attempts`` starts) and re-sends the
queue message of jobs that stayed queued for a lease length without one (a process killed between
writing a job and enqueueing it, or a worker killed between taking a message and claiming its
job). Every API replica runs it; the store's conditional writes make concurrent passes harmless.
"""

from __future__ import annotations

import logging
import math
import threading
import time

from service import metrics
from service.jobs.backends import open_blobs, open_store
from service.jobs.inputs import KIND, Submission
from service.jobs.queue import JobQueue
from service.jobs.records import CANCELED, QUEUED, Job
from service.jobs.telemetry import JobsCollector
from service.jobs.worker import EmbeddedWorkers
from service.settings import Settings

log = logging.getLogger(__name__)

MAX_RETRY_AFTER_S = 3600


class JobSystem:
    """Submit, read, list and cancel inversion jobs; ``start()``/``stop()`` in the app's lifespan."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.lease_s = settings.job_lease_s
        self.upkeep_every_s = max(0.2, self.lease_s / 3.0)
        self.workers = EmbeddedWorkers(settings) if settings.workers > 0 else None
        self._stopping = threading.Event()
        self._upkeep_thread: threading.Thread | None = None
        self._collector: JobsCollector | None = None

    # lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        self.store = open_store(self.settings)
        self.blobs = open_blobs(self.settings)
        self.queue = JobQueue(self.settings)
        self._collector = JobsCollector(self.store.stats)
        metrics.REGISTRY.register(self._collector)
        if self.workers is not None:
            self.workers.start()
        self._stopping.clear()
        self.upkeep()
        self._upkeep_thread = threading.Thread(target=self._upkeep_loop, name="jobs-upkeep", daemon=True)
        self._upkeep_thread.start()
        log.info("job system started (%s broker, %d embedded workers)", self.settings.broker, self.settings.workers)

    def stop(self) -> None:
        self._stopping.set()
        if self._upkeep_thread is not None:
            self._upkeep_thread.join()
        if self.workers is not None:
            self.workers.stop()
        if self._collector is not None:
            metrics.REGISTRY.unregister(self._collector)
            self._collector = None
        self.store.close()

    def _upkeep_loop(self) -> None:
        while not self._stopping.wait(self.upkeep_every_s):
            try:
                self.upkeep()
            except Exception:  # the store may be briefly unreachable; the next pass retries
                log.exception("job upkeep failed")

    def upkeep(self) -> None:
        """One pass: re-queue (or fail) jobs with expired leases, re-send lost queue messages."""
        for job in self.store.expire_leases():
            if job.status == QUEUED:
                log.warning("job %s: its worker's lease expired; re-queued (attempt %d of %d done)", job.id, job.attempts, job.max_attempts)
                self.queue.enqueue_inversion(job.id)
            else:
                log.warning("job %s: its worker's lease expired; now %s", job.id, job.status)
                self._notify(job)
        stale = self.store.stale_queued(time.time() - self.lease_s)
        if stale:
            pending = self.queue.pending_inversions()
            for job_id in stale:
                if job_id not in pending:
                    log.warning("job %s: queued without a queue message; enqueueing it again", job_id)
                    self.store.touch_queued(job_id)
                    self.queue.enqueue_inversion(job_id)

    def _notify(self, job: Job) -> None:
        if job.webhook:
            self.queue.enqueue_webhook(job.id)

    # the API ---------------------------------------------------------------------------------
    def submit(self, submission: Submission, idempotency_key: str | None) -> tuple[Job, bool]:
        """Create the job (or find the one this idempotency key made) and enqueue it; ``(job, created)``.

        Raises ``IdempotencyConflict`` or ``QueueFull`` (see ``TransitionStore.create``)."""
        job = Job.new(KIND, submission.request, submission.request_hash, idempotency_key=idempotency_key,
                      max_attempts=self.settings.job_max_attempts, webhook_url=submission.webhook_url)
        job, created = self.store.create(job, max_active=self.settings.limits.max_queued_jobs)
        if created:
            self.queue.enqueue_inversion(job.id)
        return job, created

    def get(self, job_id: str) -> Job | None:
        return self.store.get(job_id)

    def list(self, *, status: str | None, limit: int, before: tuple[float, str] | None) -> list[Job]:
        return self.store.list(status=status, limit=limit, before=before)

    def cancel(self, job_id: str) -> Job | None:
        job, changed = self.store.cancel(job_id)
        if changed and job.status == CANCELED:
            self._notify(job)  # canceled while queued: no worker will report it
        return job

    def retry_after(self) -> int:
        """Seconds after which a refused submission may find room: about one recent job's duration."""
        typical = self.store.stats().recent_mean_duration or self.lease_s
        return int(min(MAX_RETRY_AFTER_S, max(1, math.ceil(typical))))
