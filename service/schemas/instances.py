"""The training instances of the bundle's category."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class Attribution(BaseModel):
    """Where an instance's source mesh comes from and under which licence."""

    model_config = ConfigDict(extra="allow")

    name: str | None = None
    creator: str | None = None
    licence: str | None = None
    source: str | None = None


class Instance(BaseModel):
    id: str
    index: int = Field(description="position in the bundle's codebook")
    caption: str | None = None
    shape_id: str | None = Field(None, description="instances sharing a shape_id are colour variants of one mesh (one shape code)")
    attribution: Attribution | None = None


class InstancePage(BaseModel):
    items: list[Instance]
    total: int
    offset: int
    limit: int
    next: str | None = Field(None, description="URL of the next page, null on the last")


class InstanceQuery(BaseModel):
    offset: int = Field(0, ge=0)
    limit: int = Field(20, ge=1, le=200)
