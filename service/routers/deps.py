"""Dependencies shared by the routers: the resident bundle (503 until it is loaded) and 422 helpers."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from service.problems import ProblemError
from service.resident import Resident


def get_resident(request: Request) -> Resident:
    resident = request.app.state.resident
    if resident is None:
        error = request.app.state.load_error
        if error:
            raise ProblemError(503, "Bundle failed to load", f"{error}; fix the bundle and restart the server", kind="bundle-failed")
        raise ProblemError(503, "Not ready", "the bundle is still loading; retry shortly (GET /readyz says when it is ready)",
                           kind="not-ready", headers={"Retry-After": "1"})
    return resident


ResidentDep = Annotated[Resident, Depends(get_resident)]


def invalid(field: str, where: str, message: str, title: str = "Invalid request") -> ProblemError:
    """A 422 problem with one field error, shaped like request-validation errors."""
    return ProblemError(422, title, f"{field}: {message}", kind="validation",
                        errors=[{"field": field, "loc": [where, *field.split(".")], "message": message, "type": "value_error"}])
