"""Liveness (``/healthz``: the process answers) and readiness (``/readyz``: the bundle is loaded)."""

from __future__ import annotations

from fastapi import APIRouter, Request

from service.routers.deps import get_resident
from service.schemas.common import PROBLEM_RESPONSES
from service.schemas.health import Health, Ready

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="the process is alive")
async def healthz() -> Health:
    return Health()


@router.get("/readyz", response_model=Ready, summary="the bundle is loaded and requests can be served",
            responses={503: PROBLEM_RESPONSES[503]})
async def readyz(request: Request) -> Ready:
    resident = get_resident(request)
    return Ready(bundle=resident.bundle.digest, load_seconds=round(resident.load_seconds, 3))
