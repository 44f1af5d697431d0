"""Request body limit: a body larger than ``max_body_bytes`` is refused with 413 before it is read.

A declared ``Content-Length`` above the limit is answered at once; a body without one (chunked) is
counted as it streams in and stopped when it passes the limit, so no request can make the server
buffer more than the limit.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.problems import ProblemError, problem_response


def _too_large(limit: int) -> str:
    return f"request bodies are limited to {limit} bytes (HYPNERF_LIMITS__MAX_BODY_BYTES); send less data, e.g. smaller or fewer images"


class BodyLimitMiddleware:
    def __init__(self, app: ASGIApp, max_body_bytes: int):
        self.app = app
        self.limit = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers", ())).get(b"content-length")
        if declared is not None:
            try:
                size = int(declared)
            except ValueError:
                size = -1
            if size < 0:
                await problem_response(400, "Bad Content-Length", "the Content-Length header must be a non-negative integer",
                                       kind="bad-request")(scope, receive, send)
                return
            if size > self.limit:
                await problem_response(413, "Body too large", _too_large(self.limit), kind="body-too-large",
                                       headers={"Connection": "close"})(scope, receive, send)
                return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise ProblemError(413, "Body too large", _too_large(self.limit), kind="body-too-large")
            return message

        await self.app(scope, limited_receive, send)
