"""A worker's lease on its running job, renewed by a heartbeat thread.

The thread renews the lease every ``tick`` seconds (well inside the lease), writing the latest
progress with it, and learns on each renewal whether the job was asked to stop (cancel) or the
lease was lost (the job was presumed dead and re-queued). The optimisation polls
:meth:`Lease.should_stop` through ``invert``'s ``should_stop``, so both end the run within a step.
"""

from __future__ import annotations

import logging
import threading

from service.jobs.transitions import TransitionStore

log = logging.getLogger(__name__)

PROGRESS_INTERVAL_S = 0.5  # progress reaches the store (and clients) at most this often


class Lease:
    """The lease ``owner`` holds on ``job_id``; ``start()`` the heartbeat, ``stop()`` it when done."""

    def __init__(self, store: TransitionStore, job_id: str, owner: str, lease_s: float):
        self.store, self.job_id, self.owner, self.lease_s = store, job_id, owner, lease_s
        self.tick = min(PROGRESS_INTERVAL_S, lease_s / 3.0)
        self.cancel_requested = False
        self.lost = False
        self._progress: dict | None = None
        self._written: dict | None = None
        self._lock = threading.Lock()
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"lease-{job_id[:8]}", daemon=True)

    def start(self) -> Lease:
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the heartbeat (the final write of the job is the caller's, conditional on the lease)."""
        self._stopped.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()

    def report(self, progress: dict) -> None:
        """Record the latest progress; the heartbeat writes it."""
        with self._lock:
            self._progress = progress

    def should_stop(self) -> bool:
        return self.cancel_requested or self.lost

    def _beat(self) -> None:
        while not self._stopped.wait(self.tick):
            with self._lock:
                progress = self._progress if self._progress is not self._written else None
            try:
                renewal = self.store.renew(self.job_id, self.owner, self.lease_s, progress)
            except Exception:  # a store hiccup: the next beat retries well before the lease runs out
                log.exception("renewing the lease on job %s failed", self.job_id)
                continue
            if progress is not None:
                self._written = progress
            self.cancel_requested = renewal.cancel_requested
            if not renewal.held:
                log.warning("job %s: lease lost (re-queued or finished elsewhere); stopping this run", self.job_id)
                self.lost = True
                return
