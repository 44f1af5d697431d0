"""The SDK's one error hierarchy: the service's problem+json answers (RFC 9457) and transport failures.

::

    HypnerfError
    ├── APIError                        the server answered with an error status
    │   ├── BadRequestError             400
    │   ├── AuthenticationError         401  missing or wrong API key
    │   ├── NotFoundError               404  unknown NeRF, instance, job or route
    │   ├── ConflictError               409  idempotency key reused, job already finished
    │   ├── PayloadTooLargeError        413  body or image too large
    │   ├── UnsupportedMediaError       415  not a PNG, JPEG or WebP
    │   ├── ValidationError             422  invalid fields, listed in .errors
    │   ├── RateLimitError              429  busy; .retry_after seconds
    │   ├── NotImplementedByServerError 501  the bundle lacks the part (e.g. no query network)
    │   └── ServerError                 5xx  .retry_after on 503
    ├── ConnectionError                 no answer: refused, reset, DNS ...
    │   └── TimeoutError                no answer in time
    └── JobError                        .job, the job as last seen
        ├── JobFailedError              the job failed (.job.error says why)
        ├── JobCanceledError            the job was canceled
        └── JobTimeoutError             jobs.wait() gave up before the job finished
"""

from __future__ import annotations

import builtins
from typing import TYPE_CHECKING, Any

import httpx
from pydantic import ValidationError as _PydanticError

from hypnerf_client._retry import retry_after_seconds
from hypnerf_client.types import FieldError, Problem

if TYPE_CHECKING:
    from hypnerf_client.types import Job


class HypnerfError(Exception):
    """Base of every error this SDK raises (besides ``TypeError``/``ValueError`` for bad arguments)."""


class APIError(HypnerfError):
    """The server answered with an error status; the problem details are its body."""

    def __init__(self, status: int, title: str, detail: str | None = None, type: str = "about:blank",
                 problem: dict[str, Any] | None = None, headers: httpx.Headers | None = None):
        self.status = status
        self.title = title
        self.detail = detail
        self.type = type
        self.problem = problem or {}
        self.headers = headers or httpx.Headers()
        super().__init__(self._message())

    def _message(self) -> str:
        text = f"{self.status} {self.title}"
        return f"{text}: {self.detail}" if self.detail else text


class BadRequestError(APIError):
    """400: the request was malformed (e.g. a bad Content-Length)."""


class AuthenticationError(APIError):
    """401: send a configured key (``Client(api_key=...)`` or ``HYPNERF_API_KEY``)."""


class NotFoundError(APIError):
    """404: the NeRF, instance, job or route does not exist (an evicted NeRF is recreated by posting it again)."""


class ConflictError(APIError):
    """409: the idempotency key was used for a different request, or the job already finished."""


class PayloadTooLargeError(APIError):
    """413: the body or an image is larger than the server's limits (``ModelInfo.limits``)."""


class UnsupportedMediaError(APIError):
    """415: uploads must be PNG, JPEG or WebP."""


class ValidationError(APIError):
    """422: invalid fields; ``errors`` lists each with its dotted path and message."""

    @property
    def errors(self) -> list[FieldError]:
        try:
            return Problem.model_validate(self.problem).errors or []
        except _PydanticError:
            return []


class RateLimitError(APIError):
    """429: the server is busy (compute pool or job queue full); ``retry_after`` says when to retry."""

    @property
    def retry_after(self) -> float | None:
        return retry_after_seconds(self.headers)


class NotImplementedByServerError(APIError):
    """501: the served bundle or server version lacks what the request needs."""


class ServerError(APIError):
    """5xx: the server failed (500, quote ``problem['error_id']``) or is not ready (503)."""

    @property
    def retry_after(self) -> float | None:
        return retry_after_seconds(self.headers)


class ConnectionError(HypnerfError, builtins.ConnectionError):
    """No answer from the server: the connection was refused, reset or could not be made."""


class TimeoutError(ConnectionError, builtins.TimeoutError):
    """No answer within the client's timeout (``Client(timeout=...)``)."""


class JobError(HypnerfError):
    """A job did not end in success; ``job`` is the job as last seen."""

    def __init__(self, message: str, job: Job):
        super().__init__(message)
        self.job = job


class JobFailedError(JobError):
    """The job failed; ``job.error`` has the server's title and detail."""


class JobCanceledError(JobError):
    """The job was canceled before it finished."""


class JobTimeoutError(JobError):
    """``jobs.wait()`` reached its timeout; the job keeps running on the server."""


_BY_STATUS: dict[int, type[APIError]] = {
    400: BadRequestError, 401: AuthenticationError, 404: NotFoundError, 409: ConflictError, 413: PayloadTooLargeError,
    415: UnsupportedMediaError, 422: ValidationError, 429: RateLimitError, 501: NotImplementedByServerError,
}


def error_class(status: int) -> type[APIError]:
    """The exception class of an error status."""
    if status in _BY_STATUS:
        return _BY_STATUS[status]
    return ServerError if status >= 500 else APIError


def api_error(response: httpx.Response) -> APIError:
    """The exception for an error response (its body already read): problem+json when the server
    sent one, else the status line and the start of the body (e.g. from a proxy)."""
    problem: dict[str, Any] = {}
    try:
        body = response.json()
        if isinstance(body, dict):
            problem = body
    except ValueError:
        pass
    title = str(problem.get("title") or response.reason_phrase or "Error")
    detail = problem.get("detail")
    if detail is None and not problem:
        detail = response.text[:500].strip() or None
    cls = error_class(response.status_code)
    return cls(response.status_code, title, None if detail is None else str(detail), str(problem.get("type", "about:blank")),
               problem, response.headers)


def transport_error(exc: httpx.TransportError, method: str, url: str) -> ConnectionError:
    """The SDK's exception for an httpx transport failure."""
    if isinstance(exc, httpx.TimeoutException):
        return TimeoutError(f"{method} {url}: no answer in time ({type(exc).__name__}); raise Client(timeout=...) for slow calls")
    return ConnectionError(f"{method} {url}: {type(exc).__name__}: {exc or 'connection failed'}; is the server running at this URL?")
