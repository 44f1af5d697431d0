"""Image-upload retrieval of the nearest training instances."""

from __future__ import annotations

from pydantic import BaseModel, Field

from service.schemas.instances import Instance


class Match(BaseModel):
    instance: Instance
    score: float = Field(description="exp(-d), d the mean squared distance of the codes predicted from the image to the instance's codes in standardised units; in (0, 1], higher is closer")


class Retrieval(BaseModel):
    k: int
    matches: list[Match]
