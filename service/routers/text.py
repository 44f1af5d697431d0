"""Text-to-NeRF: a prompt -> text embedding -> the query network's codes -> a NeRF and its first view."""

from __future__ import annotations

from fastapi import APIRouter, Response

from model.prior.embedders import EmbedderError
from service.routers.deps import ResidentDep, invalid
from service.routers.nerfs import create_from_codes
from service.schemas.common import PROBLEM_RESPONSES
from service.schemas.text import ColourWord, TextNerf, TextToNerf

router = APIRouter(prefix="/v1", tags=["text"], responses={code: PROBLEM_RESPONSES[code] for code in (422, 429, 503)} | {
    501: {**PROBLEM_RESPONSES[422], "description": "the bundle has no query network"}})


@router.post("/text-to-nerf", response_model=TextNerf, status_code=201, summary="a NeRF from a text prompt (with the URL of a first render)",
             responses={200: {"description": "the prompt gave a NeRF that was already cached", "model": TextNerf}})
async def text_to_nerf(body: TextToNerf, response: Response, resident: ResidentDep) -> TextNerf:
    query = await resident.query_for("text")
    limit = resident.settings.limits.max_text_chars
    text = body.text.strip()
    if not text:
        raise invalid("text", "body", "the prompt is blank; describe the object, e.g. 'a red wooden chair'")
    if len(text) > limit:
        raise invalid("text", "body", f"at most {limit} characters (HYPNERF_LIMITS__MAX_TEXT_CHARS), got {len(text)}")
    try:
        shape, color, read = await resident.compute("text", lambda: query.text_codes(text))
    except EmbedderError as error:
        raise invalid("text", "body", str(error)) from None
    nerf = await create_from_codes(resident, shape, color, {"text": text}, response)
    return TextNerf(nerf=nerf, render_url=nerf.links.render, read_as=read.prompt,
                    colour_word=ColourWord(name=read.name, palette=read.palette) if read.name else None)
