"""Server-sent events of a job's progress (``text/event-stream``), until the job finishes.

The stream polls the jobs store (so it works the same on any API replica, whichever worker runs
the job) and sends the job, as ``GET /v1/jobs/{id}`` shows it, each time it changed: ``event: job``
with the JSON as ``data``. It ends after the event that shows a final status; a comment line keeps
idle connections open through proxies.
"""

from __future__ import annotations

import time
from collections.abc import AsyncIterator, Awaitable, Callable

import anyio

from service.jobs.records import TERMINAL
from service.schemas.jobs import JobView

POLL_S = 0.25
KEEPALIVE_S = 15.0


def sse_event(event: str, data: str, event_id: int) -> str:
    return f"id: {event_id}\nevent: {event}\ndata: {data}\n\n"


async def job_events(read: Callable[[], Awaitable[JobView | None]], disconnected: Callable[[], Awaitable[bool]]) -> AsyncIterator[str]:
    """Events of the job ``read()`` returns, until it finishes, disappears or the client leaves."""
    last, sent, quiet_since = None, 0, time.monotonic()
    while True:
        view = await read()
        if view is None:
            return
        payload = view.model_dump_json()
        if payload != last:
            sent += 1
            yield sse_event("job", payload, sent)
            last, quiet_since = payload, time.monotonic()
            if view.status in TERMINAL:
                return
        elif time.monotonic() - quiet_since > KEEPALIVE_S:
            yield ": keep-alive\n\n"
            quiet_since = time.monotonic()
        if await disconnected():
            return
        await anyio.sleep(POLL_S)
