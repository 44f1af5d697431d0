"""Prometheus metrics of this process (``service.metrics.REGISTRY``)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.metrics import REGISTRY

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=Response, summary="Prometheus text exposition: request latency by route, NeRF cache, compute pool, jobs",
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "metrics in the Prometheus text format"}})
async def metrics() -> Response:
    return Response(generate_latest(REGISTRY), media_type=CONTENT_TYPE_LATEST)
