"""Prometheus metrics of the job system (prometheus_client), read from the jobs store when scraped.

Jobs run in worker processes, possibly on other machines, so counters kept in the API process
would miss them; the store is the one place that knows every job. Every API replica therefore
reports the same, system-wide figures: queue depth, running jobs, jobs by final status and the
histogram of job durations (last start to finish).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
)
from prometheus_client.registry import Collector

from service.jobs.records import DURATION_BUCKETS, QUEUED, RUNNING, TERMINAL, JobStats

log = logging.getLogger(__name__)


class JobsCollector(Collector):
    """Exports ``stats()`` of a job store (``service.jobs.transitions.TransitionStore.stats``)."""

    def __init__(self, stats: Callable[[], JobStats]):
        self._stats = stats

    def describe(self):
        return []  # known only at scrape time; nothing to check for duplicates

    def collect(self):
        up = GaugeMetricFamily("hypnerf_jobs_store_up", "whether the jobs store answered this scrape")
        try:
            stats = self._stats()
        except Exception as exc:  # a scrape must not fail because the store is briefly unreachable
            log.warning("jobs store unavailable for metrics: %s", exc, exc_info=True)
            up.add_metric([], 0)
            yield up
            return
        up.add_metric([], 1)
        yield up
        yield GaugeMetricFamily("hypnerf_jobs_queue_depth", "inversion jobs waiting for a worker", value=stats.by_status.get(QUEUED, 0))
        yield GaugeMetricFamily("hypnerf_jobs_running", "inversion jobs being run by a worker", value=stats.by_status.get(RUNNING, 0))
        finished = CounterMetricFamily("hypnerf_jobs_finished", "inversion jobs by final status", labels=["status"])
        for status in TERMINAL:
            finished.add_metric([status], stats.by_status.get(status, 0))
        yield finished
        buckets = [(repr(bound), count) for bound, count in zip(DURATION_BUCKETS, stats.duration_buckets)]
        buckets.append(("+Inf", stats.duration_buckets[-1]))
        yield HistogramMetricFamily("hypnerf_job_duration_seconds", "inversion job durations, last start to finish",
                                    buckets=buckets, sum_value=stats.duration_sum)
