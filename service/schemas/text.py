"""Text-to-NeRF."""

from __future__ import annotations

from pydantic import BaseModel, Field

from service.schemas.nerfs import Nerf


class TextToNerf(BaseModel):
    text: str = Field(min_length=1, max_length=10_000, description="a description of the object, e.g. 'a red wooden chair'",
                      examples=["a brown chair"])


class ColourWord(BaseModel):
    name: str = Field(description="the colour name found in the prompt", examples=["crimson"])
    palette: str = Field(description="the palette colour it was read as", examples=["red"])


class TextNerf(BaseModel):
    nerf: Nerf
    render_url: str = Field(description="a first view of it (GET returns a PNG)")
    read_as: str = Field(description="the prompt as the query network read it: a colour name that is not a palette colour "
                                     "is replaced by the palette colour nearest it", examples=["a red high chair"])
    colour_word: ColourWord | None = Field(default=None, description="the colour name that was replaced, if any")
