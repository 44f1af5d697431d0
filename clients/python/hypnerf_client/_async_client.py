"""``AsyncClient``: the asyncio client, on ``httpx.AsyncClient``; the same methods as ``Client``,
awaited. Requests, parsing and retry decisions are shared with it (``_calls``, ``_config``)."""

from __future__ import annotations

import asyncio
import os
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Self, TypeVar, Unpack

import httpx

from hypnerf_client import _calls as calls
from hypnerf_client._calls import Call, ImageInput, InstanceRef, JobRef, MeshOptions, NerfRef, Pose, RenderOptions, TurntableOptions
from hypnerf_client._config import DEFAULT_TIMEOUT, UNSET, Config, Timeout
from hypnerf_client._sse import SSEDecoder
from hypnerf_client.errors import api_error, transport_error
from hypnerf_client.types import (CacheStats, Codes, Health, Instance, InstancePage, Interpolation, InversionOptions, Job, JobEvent,
                                  JobList, JobStatus, Mix, ModelInfo, Nerf, Ready, Retrieval, TextNerf)

T = TypeVar("T")


class AsyncClient:
    """The asyncio twin of ``Client`` (same arguments, same methods, awaited)::

        async with AsyncClient() as client:
            nerf = await client.nerfs.create(instance=...)
    """

    def __init__(self, base_url: str | None = None, *, api_key: str | None = None, timeout: Timeout = DEFAULT_TIMEOUT,
                 max_retries: int = 2, backoff: float = 0.5, headers: Mapping[str, str] | None = None,
                 http_client: httpx.AsyncClient | None = None):
        self._config = Config.create(base_url, api_key, timeout, max_retries, backoff, headers)
        self._http = http_client or httpx.AsyncClient()
        self._owns_http = http_client is None
        self._bind()

    def _bind(self) -> None:
        self.instances = AsyncInstances(self)
        self.nerfs = AsyncNerfs(self)
        self.jobs = AsyncJobs(self)

    @property
    def base_url(self) -> str:
        return self._config.base_url

    def with_options(self, *, timeout: Timeout | object = UNSET, max_retries: int | None = None) -> AsyncClient:
        """A client sharing this one's connections with another timeout or retry count."""
        clone = object.__new__(AsyncClient)
        clone._config = self._config.replace(timeout, max_retries)
        clone._http, clone._owns_http = self._http, False
        clone._bind()
        return clone

    async def close(self) -> None:
        if self._owns_http:
            await self._http.aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    def __repr__(self) -> str:
        return f"AsyncClient({self.base_url!r})"

    async def _send(self, call: Call) -> httpx.Response:
        retries = 0
        while True:
            request = self._config.build(self._http, call)
            try:
                response = await self._http.send(request, stream=call.stream)
            except httpx.TransportError as error:
                delay = self._config.retry_delay(call, retries, error=error)
                if delay is None:
                    raise transport_error(error, call.method, str(request.url)) from error
            else:
                if not response.is_error:
                    return response
                delay = self._config.retry_delay(call, retries, response=response)
                await response.aread()
                await response.aclose()
                if delay is None:
                    raise api_error(response)
            await asyncio.sleep(delay)
            retries += 1

    async def _run(self, call: Call[T]) -> T:
        return call.parse(await self._send(call))

    async def health(self) -> Health:
        return await self._run(calls.health())

    async def ready(self) -> Ready:
        return await self._run(calls.ready())

    async def model(self) -> ModelInfo:
        return await self._run(calls.model_info())

    async def cache(self) -> CacheStats:
        return await self._run(calls.cache_stats())

    async def metrics(self) -> str:
        return await self._run(calls.metrics())

    async def text_to_nerf(self, prompt: str) -> TextNerf:
        return await self._run(calls.text_to_nerf(prompt))

    async def retrieve(self, image: ImageInput, k: int = 5) -> Retrieval:
        return await self._run(calls.retrieve(image, k))


class AsyncInstances:
    """``client.instances`` of an ``AsyncClient``."""

    def __init__(self, client: AsyncClient):
        self._client = client

    async def list(self, *, limit: int = 20, offset: int = 0) -> InstancePage:
        return await self._client._run(calls.list_instances(limit, offset))

    async def iter_all(self, *, page_size: int = 100) -> AsyncIterator[Instance]:
        offset = 0
        while True:
            page = await self.list(limit=page_size, offset=offset)
            for item in page.items:
                yield item
            offset = page.offset + len(page.items)
            if page.next is None or not page.items:
                return

    async def get(self, instance: InstanceRef) -> Instance:
        return await self._client._run(calls.get_instance(instance))


class AsyncNerfs:
    """``client.nerfs`` of an ``AsyncClient``."""

    def __init__(self, client: AsyncClient):
        self._client = client

    async def create(self, *, instance: InstanceRef | None = None, codes: Codes | Mapping | Sequence | None = None,
                     mix: Mix | Mapping | Sequence | None = None, interpolate: Interpolation | Mapping | Sequence | None = None) -> Nerf:
        return await self._client._run(calls.create_nerf(instance, codes, mix, interpolate))

    async def get(self, nerf: NerfRef) -> Nerf:
        return await self._client._run(calls.get_nerf(nerf))

    async def render(self, nerf: NerfRef, **options: Unpack[RenderOptions]) -> bytes:
        return await self._client._run(calls.render(nerf, options))

    async def save_render(self, nerf: NerfRef, path: str | os.PathLike, **options: Unpack[RenderOptions]) -> Path:
        return await asyncio.to_thread(calls.write_file, path, await self.render(nerf, **options))

    async def turntable(self, nerf: NerfRef, **options: Unpack[TurntableOptions]) -> bytes:
        return await self._client._run(calls.turntable(nerf, options))

    async def save_turntable(self, nerf: NerfRef, path: str | os.PathLike, **options: Unpack[TurntableOptions]) -> Path:
        return await asyncio.to_thread(calls.write_file, path, await self.turntable(nerf, **options))

    async def mesh(self, nerf: NerfRef, **options: Unpack[MeshOptions]) -> bytes:
        return await self._client._run(calls.mesh(nerf, options))

    async def save_mesh(self, nerf: NerfRef, path: str | os.PathLike, **options: Unpack[MeshOptions]) -> Path:
        data = await self._client._run(calls.mesh(nerf, calls.mesh_options_for(path, options)))
        return await asyncio.to_thread(calls.write_file, path, data)


class AsyncJobs:
    """``client.jobs`` of an ``AsyncClient``."""

    def __init__(self, client: AsyncClient):
        self._client = client

    async def create_inversion(self, images: ImageInput | Sequence[ImageInput], *, poses: Sequence[Pose] | None = None,
                               masks: ImageInput | Sequence[ImageInput] | None = None,
                               options: InversionOptions | Mapping[str, Any] | None = None, idempotency_key: str | None = None) -> Job:
        call = await asyncio.to_thread(calls.create_inversion, images, poses, masks, options, idempotency_key)  # reads files
        return await self._client._run(call)

    async def get(self, job: JobRef) -> Job:
        return await self._client._run(calls.get_job(job))

    async def cancel(self, job: JobRef) -> Job:
        return await self._client._run(calls.cancel_job(job))

    async def list(self, *, status: JobStatus | None = None, limit: int = 20, cursor: str | None = None) -> JobList:
        return await self._client._run(calls.list_jobs(status, limit, cursor))

    async def iter_all(self, *, status: JobStatus | None = None, page_size: int = 100) -> AsyncIterator[Job]:
        cursor = None
        while True:
            page = await self.list(status=status, limit=page_size, cursor=cursor)
            for item in page.items:
                yield item
            if page.next is None:
                return
            cursor = page.next

    async def wait(self, job: JobRef, *, timeout: float | None = None, poll_interval: float = 0.5,
                   on_progress: Callable[[Job], Any] | None = None) -> Job:
        watch = calls.JobWatch(calls.job_id(job), timeout, poll_interval, on_progress)
        while not watch.finished(await self.get(watch.job)):
            await asyncio.sleep(watch.pause())
        return watch.seen

    async def events(self, job: JobRef) -> AsyncIterator[JobEvent]:
        response = await self._client._send(calls.job_events(job))
        decoder = SSEDecoder()
        try:
            async for line in response.aiter_lines():
                event = decoder.decode(line)
                if event is not None and (parsed := calls.job_event(event)) is not None:
                    yield parsed
        except httpx.TransportError as error:
            raise transport_error(error, "GET", str(response.request.url)) from error
        finally:
            await response.aclose()
