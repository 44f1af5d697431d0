"""The bundle's training instances, paginated, with captions and attribution."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from service.problems import ProblemError
from service.routers.deps import ResidentDep
from service.schemas.common import PROBLEM_RESPONSES
from service.schemas.instances import Instance, InstancePage, InstanceQuery

router = APIRouter(prefix="/v1/instances", tags=["instances"], responses={422: PROBLEM_RESPONSES[422], 503: PROBLEM_RESPONSES[503]})


def instance_view(index: int, record: dict) -> Instance:
    return Instance(id=record["id"], index=index, caption=record.get("caption"), shape_id=record.get("shape_id"),
                    attribution=record.get("attribution"))


@router.get("", response_model=InstancePage, summary="training instances, `limit` per page from `offset`")
async def list_instances(request: Request, resident: ResidentDep, page: Annotated[InstanceQuery, Query()]) -> InstancePage:
    records = resident.bundle.instances
    stop = min(page.offset + page.limit, len(records))
    items = [instance_view(i, records[i]) for i in range(page.offset, stop)]
    following = str(request.url.include_query_params(offset=stop, limit=page.limit)) if stop < len(records) else None
    return InstancePage(items=items, total=len(records), offset=page.offset, limit=page.limit, next=following)


@router.get("/{instance_id}", response_model=Instance, summary="one training instance", responses={404: PROBLEM_RESPONSES[404]})
async def get_instance(instance_id: str, resident: ResidentDep) -> Instance:
    if instance_id not in resident.ids:
        raise ProblemError(404, "Unknown instance", f"{instance_id!r} is not an instance of this bundle; list them with GET /v1/instances",
                           kind="unknown-instance")
    index = resident.ids[instance_id]
    return instance_view(index, resident.bundle.instances[index])
