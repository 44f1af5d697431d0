"""Schemas shared by several resources: problem details, finite numbers, NeRF ids."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
NERF_ID_PATTERN = r"^[0-9a-f]{64}$"


class FieldError(BaseModel):
    field: str = Field(description="dotted path of the offending field, e.g. `codes.shape` or `width`")
    loc: list[str] = Field(description="where the field is: `body`, `query` or `path`, then its path")
    message: str
    type: str


class Problem(BaseModel):
    """RFC 9457 problem details (``application/problem+json``), the body of every error."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"examples": [{
        "type": "urn:hypnerf:problem:unknown-nerf", "title": "Unknown NeRF", "status": 404,
        "detail": "no NeRF 3f0c... in the cache; create it with POST /v1/nerfs (ids are content addresses, so the same request gives the same id)",
    }]})

    type: str = Field("about:blank", description="`urn:hypnerf:problem:<kind>` or `about:blank`")
    title: str
    status: int
    detail: str | None = None
    instance: str | None = None
    errors: list[FieldError] | None = Field(None, description="field errors of a 422")


PROBLEM_RESPONSES = {
    code: {"model": Problem, "content": {"application/problem+json": {}}, "description": text}
    for code, text in {401: "missing or wrong API key", 404: "unknown resource", 413: "body or image too large",
                       415: "unsupported media type", 422: "invalid request (field errors listed)",
                       429: "too busy; retry after the Retry-After header's seconds", 503: "the bundle is not loaded yet"}.items()
}
"""OpenAPI entries for the errors every v1 route may answer."""
