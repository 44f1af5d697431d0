"""When a failed call is retried, and after how long: exponential backoff with jitter, honouring
the server's ``Retry-After`` (RFC 9110: seconds or an HTTP date).

The decisions are pure functions of the attempt, the answer (or transport failure) and whether the
call may be repeated, shared by ``Client`` and ``AsyncClient``. A call is repeated only when that
is safe: the request never left (connection refused), or the call is idempotent (reads, content-
addressed creation, and job submission, which carries an ``Idempotency-Key``).
"""

from __future__ import annotations

import email.utils
import math
import random
import time
from collections.abc import Mapping
from dataclasses import dataclass

import httpx

# 408 and 429 and the gateway/unavailable family: the server did not do the work, or may succeed later.
# A 500 is a server bug (the service answers unexpected errors with 500): repeating it does not help.
RETRY_STATUSES = frozenset({408, 429, 502, 503, 504})
# failures where the request certainly never reached the server: safe to repeat for any call
NOT_SENT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout)


def retry_after_seconds(headers: Mapping[str, str]) -> float | None:
    """The ``Retry-After`` header in seconds from now (``None`` when absent or unreadable)."""
    value = headers.get("retry-after")
    if value is None:
        return None
    value = value.strip()
    try:
        seconds = float(value)
    except ValueError:
        try:
            when = email.utils.parsedate_to_datetime(value)
        except (TypeError, ValueError):
            return None
        seconds = when.timestamp() - time.time()
    return None if math.isnan(seconds) else max(0.0, seconds)


@dataclass(frozen=True)
class RetryPolicy:
    """``max_retries`` repeats after the first attempt; the n-th waits ``backoff * 2**n`` seconds
    (at most ``max_backoff``) times a jitter in [0.75, 1], or the server's ``Retry-After`` plus up
    to 10%. A ``Retry-After`` above ``max_retry_after`` is not waited for: the error is raised with it."""

    max_retries: int = 2
    backoff: float = 0.5
    max_backoff: float = 8.0
    max_retry_after: float = 60.0

    def __post_init__(self):
        if self.max_retries < 0:
            raise ValueError(f"max_retries must be 0 or more, got {self.max_retries}")
        if self.backoff < 0 or self.max_backoff < 0:
            raise ValueError("backoff and max_backoff must be 0 or more seconds")

    def wait(self, retries_done: int, retry_after: float | None = None) -> float:
        """Seconds to sleep before retry number ``retries_done + 1``."""
        if retry_after is not None:
            return retry_after + random.uniform(0.0, 0.1 * retry_after)
        return min(self.max_backoff, self.backoff * 2.0 ** retries_done) * random.uniform(0.75, 1.0)

    def after_status(self, retries_done: int, status: int, headers: Mapping[str, str], idempotent: bool) -> float | None:
        """Seconds to wait before repeating a call answered ``status``, or ``None`` to raise."""
        if retries_done >= self.max_retries or status not in RETRY_STATUSES or not idempotent:
            return None
        retry_after = retry_after_seconds(headers)
        if retry_after is not None and retry_after > self.max_retry_after:
            return None
        return self.wait(retries_done, retry_after)

    def after_transport(self, retries_done: int, error: httpx.TransportError, idempotent: bool) -> float | None:
        """Seconds to wait before repeating a call that got no answer, or ``None`` to raise."""
        if retries_done >= self.max_retries or not (idempotent or isinstance(error, NOT_SENT)):
            return None
        return self.wait(retries_done)
