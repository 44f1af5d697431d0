"""The promises every jobs store keeps (SQLite and Redis alike), checked on a real store: the
idempotency key, the cap on active jobs, claims, leases that renew, expire, re-queue and finally
fail, finishing only under the lease, cancel, listing and the statistics behind the metrics."""

from __future__ import annotations

import time

import pytest

from service.jobs.records import IdempotencyConflict, Job, QueueFull
from service.jobs.transitions import TransitionStore

LEASE_S = 0.3


def new_job(key: str | None = None, request_hash: str = "h1") -> Job:
    return Job.new("inversion", {"images": ["a"]}, request_hash, idempotency_key=key, max_attempts=2, webhook_url=None)


def check_store(store: TransitionStore) -> None:
    first, created = store.create(new_job("key-1"), max_active=2)
    assert created and store.get(first.id).status == "queued"
    again, created = store.create(new_job("key-1"), max_active=2)
    assert not created and again.id == first.id
    with pytest.raises(IdempotencyConflict):
        store.create(new_job("key-1", request_hash="h2"), max_active=2)
    second, _ = store.create(new_job(), max_active=2)
    with pytest.raises(QueueFull):
        store.create(new_job(), max_active=2)
    assert store.count_active() == 2

    # a queued job is canceled at once, and only once
    canceled, changed = store.cancel(second.id)
    assert changed and canceled.status == "canceled" and canceled.finished_at is not None
    assert store.cancel(second.id) == (store.get(second.id), False)

    # claims, renewals, expiry and re-queueing, finishing only under the lease
    running = store.claim(first.id, "w1", LEASE_S)
    assert running.status == "running" and running.attempts == 1 and running.lease_owner == "w1"
    assert store.claim(first.id, "w2", LEASE_S) is None  # taken
    assert not store.renew(first.id, "w2", LEASE_S).held
    assert store.renew(first.id, "w1", LEASE_S, {"step": 3, "steps": 10}).held
    assert store.get(first.id).progress == {"step": 3, "steps": 10}
    time.sleep(LEASE_S + 0.1)
    assert [j.status for j in store.expire_leases()] == ["queued"]
    assert not store.finish(first.id, "w1", "succeeded")  # the presumed-dead worker may not finish it
    assert store.claim(first.id, "w2", LEASE_S).attempts == 2
    assert store.release(first.id, "w2") and store.get(first.id).status == "queued"
    assert store.claim(first.id, "w3", LEASE_S).attempts == 3
    time.sleep(LEASE_S + 0.1)
    failed = store.expire_leases()
    assert [j.status for j in failed] == ["failed"] and "started 3 times" in failed[0].error["detail"]

    # a running job asked to stop: its worker learns it; if the worker is gone, the job ends canceled
    third, _ = store.create(new_job(), max_active=2)
    store.claim(third.id, "w1", LEASE_S)
    asked, changed = store.cancel(third.id)
    assert changed and asked.status == "running" and asked.cancel_requested
    assert store.renew(third.id, "w1", LEASE_S).cancel_requested
    time.sleep(LEASE_S + 0.1)
    assert [j.status for j in store.expire_leases()] == ["canceled"]

    fourth, _ = store.create(new_job(), max_active=2)
    assert store.stale_queued(time.time() + 1) == [fourth.id] and store.stale_queued(fourth.queued_at - 1) == []
    store.claim(fourth.id, "w1", LEASE_S)
    assert store.finish(fourth.id, "w1", "succeeded", result={"nerf_id": "0" * 64})
    assert not store.finish(fourth.id, "w1", "succeeded")  # exactly once
    store.record_webhook(fourth.id, {"delivered": True, "attempts": 1})
    assert store.get(fourth.id).result == {"nerf_id": "0" * 64} and store.get(fourth.id).webhook == {"delivered": True, "attempts": 1}

    newest = store.list(status=None, limit=2, before=None)
    assert [j.id for j in newest] == [fourth.id, third.id]
    rest = store.list(status=None, limit=5, before=(newest[-1].created_at, newest[-1].id))
    assert [j.id for j in rest] == [second.id, first.id]
    assert [j.id for j in store.list(status="canceled", limit=10, before=None)] == [third.id, second.id]

    stats = store.stats()
    assert stats.by_status == {"succeeded": 1, "failed": 1, "canceled": 2}
    assert stats.duration_buckets[-1] == 3  # the three that ran; the one canceled while queued did not
    assert stats.duration_buckets[0] == 3 and stats.recent_mean_duration is not None and stats.duration_sum > 0
