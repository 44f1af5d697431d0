"""Text-to-NeRF."""

from __future__ import annotations

from pydantic import BaseModel, Field

from service.schemas.nerfs import Nerf


class TextToNerf(BaseModel):
    text: str = Field(min_length=1, max_length=10_000, description="a description of the object, e.g. 'a red wooden chair'",
                      examples=["a brown chair"])


class TextNerf(BaseModel):
    nerf: Nerf
    render_url: str = Field(description="a first view of it (GET returns a PNG)")
