"""Retrieval: an uploaded image -> image embedding -> the training instances most similar to it."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, UploadFile

from model.prior.embedders import EmbedderError
from service.routers.deps import ResidentDep, invalid
from service.routers.instances import instance_view
from service.schemas.common import PROBLEM_RESPONSES
from service.schemas.retrieve import Match, Retrieval
from service.uploads import decode_image

router = APIRouter(prefix="/v1", tags=["retrieve"], responses={code: PROBLEM_RESPONSES[code] for code in (413, 415, 422, 429, 503)} | {
    501: {**PROBLEM_RESPONSES[422], "description": "the bundle has no query network"}})


@router.post("/retrieve", response_model=Retrieval, summary="the k training instances nearest an uploaded image (PNG, JPEG or WebP)")
async def retrieve(resident: ResidentDep, image: Annotated[UploadFile, File(description="PNG, JPEG or WebP; alpha, if any, masks the object")],
                   k: Annotated[int, Form(ge=1, description="how many instances to return (at most limits.max_retrieve_k)")] = 5) -> Retrieval:
    query = await resident.query_for("image")
    limit = resident.settings.limits.max_retrieve_k
    if k > limit:
        raise invalid("k", "body", f"at most {limit} (HYPNERF_LIMITS__MAX_RETRIEVE_K), got {k}")
    data = await image.read()
    rgba = await resident.compute("decode", lambda: decode_image(data, max_pixels=resident.settings.limits.max_image_pixels, name="image"))
    try:
        indices, scores = await resident.compute("retrieve", lambda: query.retrieve(query.embed_image(rgba), k))
    except EmbedderError as error:
        raise invalid("image", "body", str(error), "Image cannot be embedded") from None
    instances = resident.bundle.instances
    return Retrieval(k=k, matches=[Match(instance=instance_view(int(i), instances[int(i)]), score=float(s)) for i, s in zip(indices, scores)])
