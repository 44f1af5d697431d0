"""Where the job system keeps its state, chosen by ``settings.broker``.

``sqlite`` (the default, one machine): the jobs table and huey's queue in SQLite files under
``<state_dir>/jobs``, uploaded inputs as files beside them. ``redis`` (several machines): job
records, inputs and huey's queue in the Redis database at ``settings.redis_url``, so API replicas
and workers anywhere see the same jobs; only the NeRF cache directory must be shared disk.
"""

from __future__ import annotations

from huey import RedisHuey, SqliteHuey
from huey.api import Huey

from service.jobs.blobs import DiskBlobs, RedisBlobs
from service.jobs.redis_store import RedisJobStore
from service.jobs.store import SqliteJobStore
from service.jobs.transitions import TransitionStore
from service.settings import Settings

QUEUE_NAME = "hypnerf"


def open_store(settings: Settings) -> TransitionStore:
    if settings.broker == "redis":
        return RedisJobStore(settings.redis_url, prefix=QUEUE_NAME)
    return SqliteJobStore(settings.state_dir / "jobs" / "jobs.db")


def open_blobs(settings: Settings) -> DiskBlobs | RedisBlobs:
    if settings.broker == "redis":
        return RedisBlobs(settings.redis_url, prefix=QUEUE_NAME)
    return DiskBlobs(settings.state_dir / "jobs" / "inputs")


def open_huey(settings: Settings) -> Huey:
    """huey without result storage: outcomes live in the jobs table, not in huey."""
    if settings.broker == "redis":
        return RedisHuey(QUEUE_NAME, url=settings.redis_url, results=False)
    path = settings.state_dir / "jobs" / "queue.db"
    path.parent.mkdir(parents=True, exist_ok=True)
    return SqliteHuey(QUEUE_NAME, filename=str(path), results=False)
