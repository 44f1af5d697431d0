"""Worker processes: huey's consumer with process workers running the job system's tasks.

``python -m service.jobs`` runs a consumer with ``HYPNERF_WORKERS`` worker processes
(at least one) configured from ``HYPNERF_*`` settings: that is how workers run on other machines
(``HYPNERF_BROKER=redis``). The server starts the same command itself when ``workers > 0``
(:class:`EmbeddedWorkers`), handing it its settings on stdin, and the consumer follows the server
out: when its parent dies (even by SIGKILL) it stops its workers, and a worker whose consumer
died stops too, so no process outlives the server and keeps a lease it cannot renew for long.

Stopping a worker mid-job (SIGTERM, huey's immediate shutdown) interrupts the task, which puts
the job back in the queue; a worker killed outright leaves a lease that expires and the job is
re-queued by the next API process's upkeep.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from pydantic import SecretStr

from service.jobs.queue import JobQueue
from service.settings import Settings

log = logging.getLogger(__name__)

WATCH_INTERVAL_S = 0.5
POLL_MAX_DELAY_S = 0.5  # longest wait between two looks at an empty SQLite queue


def settings_payload(settings: Settings) -> str:
    """The settings as JSON with secrets revealed (sent over a pipe, never on a command line)."""
    def reveal(value):
        if isinstance(value, SecretStr):
            return value.get_secret_value()
        if isinstance(value, Path):
            return str(value)
        raise TypeError(f"cannot serialise {type(value).__name__}")
    return json.dumps(settings.model_dump(), default=reveal)


def _watch_parent(on_orphaned) -> None:
    """Call ``on_orphaned()`` once this process's parent has gone (checked every half second)."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(WATCH_INTERVAL_S)
        on_orphaned()

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _stop_orphaned_worker() -> None:
    log.warning("worker %d: its consumer is gone; stopping", os.getpid())
    os.kill(os.getpid(), signal.SIGTERM)  # interrupts a running task, which re-queues its job
    time.sleep(3.0)
    os._exit(1)


def run_consumer(settings: Settings, *, exit_with_parent: bool) -> None:
    queue = JobQueue(settings)
    queue.huey.on_startup("watch-consumer")(lambda: _watch_parent(_stop_orphaned_worker))
    consumer = queue.huey.create_consumer(
        workers=max(1, settings.workers), worker_type="process", periodic=False, check_worker_health=True,
        health_check_interval=1, initial_delay=0.05, backoff=1.5, max_delay=POLL_MAX_DELAY_S)
    if exit_with_parent:
        def parent_gone() -> None:
            log.warning("consumer %d: the server is gone; stopping the workers", os.getpid())
            os.kill(os.getpid(), signal.SIGTERM)
        _watch_parent(parent_gone)
    consumer.run()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service.jobs",
                                     description="Run inversion workers (huey consumer) with the HYPNERF_* settings.")
    parser.add_argument("--settings-stdin", action="store_true", help="read the settings as JSON from stdin instead of the environment")
    parser.add_argument("--exit-with-parent", action="store_true", help="stop when the process that started this one exits")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(process)d %(name)s %(levelname)s %(message)s")
    settings = Settings.model_validate(json.loads(sys.stdin.read())) if args.settings_stdin else Settings()
    run_consumer(settings, exit_with_parent=args.exit_with_parent)
    return 0


class EmbeddedWorkers:
    """The worker processes a server starts for itself (``settings.workers`` of them)."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.process: subprocess.Popen | None = None

    def start(self) -> None:
        root = str(Path(__file__).resolve().parents[2])
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
        self.process = subprocess.Popen([sys.executable, "-m", "service.jobs", "--settings-stdin", "--exit-with-parent"],
                                        stdin=subprocess.PIPE, env=env)
        self.process.stdin.write(settings_payload(self.settings).encode())
        self.process.stdin.close()
        log.info("started %d inversion worker process(es) under consumer %d", self.settings.workers, self.process.pid)

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the consumer (running jobs go back to the queue); kill it if it does not stop in time."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            log.warning("worker consumer %d did not stop within %.0f s; killing it", self.process.pid, timeout)
            self.process.kill()
            self.process.wait()

