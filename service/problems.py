"""Errors as RFC 9457 problem details (``application/problem+json``), for every error the service
answers: its own (``ProblemError``), routing (404, 405), request validation (422 with the field
errors), body size (413), media types (415), back-pressure (429 with ``Retry-After``) and anything
unexpected (500 with an id to quote, the traceback only in the log).

``ProblemError`` subclasses Starlette's ``HTTPException`` so it passes unchanged through
FastAPI's body parsing (a limit hit while a body streams in stays a 413, not a generic 400).
"""

from __future__ import annotations

import logging
import uuid
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Receive, Scope, Send

log = logging.getLogger(__name__)

PROBLEM_JSON = "application/problem+json"
TYPE_PREFIX = "urn:hypnerf:problem:"


def _phrase(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


class ProblemError(StarletteHTTPException):
    """An error answered as problem+json: ``ProblemError(404, "Unknown NeRF", "no NeRF ...", kind="unknown-nerf")``.

    ``kind`` names the problem type (``urn:hypnerf:problem:<kind>``; default ``about:blank``),
    ``headers`` are added to the response (e.g. ``Retry-After``), ``extra`` become members of
    the problem object.
    """

    def __init__(self, status: int, title: str | None = None, detail: str = "", *, kind: str | None = None,
                 headers: dict[str, str] | None = None, **extra):
        super().__init__(status_code=status, detail=detail, headers=headers)
        self.status = status
        self.title = title or _phrase(status)
        self.kind = kind
        self.extra = extra


def problem_response(status: int, title: str | None = None, detail: str = "", *, kind: str | None = None,
                     headers: dict[str, str] | None = None, instance: str | None = None, **extra) -> JSONResponse:
    body = {"type": TYPE_PREFIX + kind if kind else "about:blank", "title": title or _phrase(status), "status": status}
    if detail:
        body["detail"] = detail
    if instance:
        body["instance"] = instance
    body.update(extra)
    return JSONResponse(body, status_code=status, headers=headers, media_type=PROBLEM_JSON)


_STATUS_KINDS = {401: "unauthorized", 404: "not-found", 405: "method-not-allowed", 413: "body-too-large",
                 415: "unsupported-media-type", 429: "too-many-requests"}


async def _problem_error(request: Request, exc: ProblemError) -> JSONResponse:
    return problem_response(exc.status, exc.title, exc.detail, kind=exc.kind, headers=exc.headers, **exc.extra)


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    detail = exc.detail if isinstance(exc.detail, str) and exc.detail != _phrase(exc.status_code) else ""
    if exc.status_code == 404 and not detail:
        detail = f"no resource at {request.url.path}; the API is described at /docs and /openapi.json"
    if exc.status_code == 405 and not detail:
        detail = f"{request.method} is not allowed on {request.url.path}; allowed: {exc.headers.get('Allow', '?') if exc.headers else '?'}"
    return problem_response(exc.status_code, detail=detail, kind=_STATUS_KINDS.get(exc.status_code), headers=exc.headers)


def field_errors(errors) -> list[dict]:
    """Pydantic's errors as ``{"field", "loc", "message", "type"}``, without echoing the input.

    A discriminated union puts the tag in ``loc`` before the field of the same name
    (``body.codes.codes.shape``); the repeat is dropped. JSON syntax errors name the position.
    """
    out = []
    for err in errors:
        loc: list[str] = []
        for part in (str(p) for p in err.get("loc", ())):
            if not loc or loc[-1] != part:
                loc.append(part)
        message, kind = str(err.get("msg", "")), str(err.get("type", ""))
        if kind == "json_invalid":
            reason = (err.get("ctx") or {}).get("error", "")
            message = f"the body is not valid JSON ({reason} at character {loc[-1]})" if reason else "the body is not valid JSON"
            loc = loc[:1]
        out.append({"field": ".".join(loc[1:]) if len(loc) > 1 else ".".join(loc), "loc": loc, "message": message, "type": kind})
    return out


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    errors = field_errors(exc.errors())
    summary = "; ".join(f"{e['field'] or 'body'}: {e['message']}" for e in errors[:5])
    return problem_response(422, "Invalid request", summary, kind="validation", errors=errors)


def install_problem_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ProblemError, _problem_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)


class CatchAllMiddleware:
    """Outermost ASGI middleware: an unexpected exception becomes a generic 500 problem carrying an
    error id; the traceback goes to the log under that id, never to the client."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked_send(message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracked_send)
        except Exception:
            error_id = uuid.uuid4().hex
            log.exception("unhandled error %s on %s %s", error_id, scope.get("method"), scope.get("path"))
            if started:
                return  # the response is under way; the client sees a truncated body
            response = problem_response(500, detail=f"an unexpected error occurred; quote error id {error_id} when reporting it",
                                        kind="internal", instance=f"urn:uuid:{uuid.UUID(error_id)}", error_id=error_id)
            await response(scope, receive, send)
