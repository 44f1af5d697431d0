"""What the server serves (``/v1/model``) and how its NeRF cache is doing (``/v1/cache``)."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter

from service.routers.deps import ResidentDep
from service.schemas.common import PROBLEM_RESPONSES
from service.schemas.model import (
    BundleInfo,
    CacheStats,
    CameraInfo,
    CodeDims,
    ModelInfo,
)

router = APIRouter(prefix="/v1", tags=["model"], responses={503: PROBLEM_RESPONSES[503]})


@router.get("/model", response_model=ModelInfo, summary="the bundle: digest, format, components, field config, instances, limits")
async def model_info(resident: ResidentDep) -> ModelInfo:
    bundle = resident.bundle
    return ModelInfo(
        bundle=BundleInfo(digest=bundle.digest, format=bundle.manifest.get("format"), created=bundle.manifest.get("created"),
                          components=bundle.manifest.get("components", [])),
        field=resident.field_config(),
        scene_box=bundle.scene.to_aabb(),
        camera=CameraInfo(width=bundle.camera.width, height=bundle.camera.height, fov_degrees=resident.default_fov,
                          radius=resident.default_radius),
        codes=CodeDims(shape=bundle.shape_codes.shape[1], color=bundle.color_codes.shape[1]),
        instances=len(bundle.instances),
        grid_resolution=resident.grid_resolution,
        text_to_nerf=bundle.query is not None and "text" in bundle.query.modalities,
        retrieval=resident.retrieval_ready,
        limits=resident.settings.limits,
    )


@router.get("/cache", response_model=CacheStats, summary="NeRF cache hits, misses, evictions and bytes (this process)")
async def cache_stats(resident: ResidentDep) -> CacheStats:
    return CacheStats(**await asyncio.to_thread(resident.cache.stats))
