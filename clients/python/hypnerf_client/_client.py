"""``Client``: the synchronous client, on ``httpx.Client`` (connection pooling, HTTP/1.1 keep-alive).

Every method is one ``_calls.Call`` sent with retries; the request building, parsing and retry
decisions are shared with ``AsyncClient``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
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


class Client:
    """A client of one hypnerf server.

    ``base_url`` defaults to ``$HYPNERF_URL``, else ``http://127.0.0.1:8000``; ``api_key`` (sent as
    ``Authorization: Bearer``) to ``$HYPNERF_API_KEY``. ``timeout`` is in seconds per request
    (``None``: no limit). Failed calls are retried ``max_retries`` times with exponential backoff
    (from ``backoff`` seconds, with jitter) or after the server's ``Retry-After``: on 408, 429, 502,
    503, 504 and lost connections for calls that are safe to repeat, and on refused connections for
    any call. Pass ``http_client`` to use your own ``httpx.Client`` (proxies, certificates); the
    client then leaves closing it to you. Use it as a context manager, or call ``close()``.
    """

    def __init__(self, base_url: str | None = None, *, api_key: str | None = None, timeout: Timeout = DEFAULT_TIMEOUT,
                 max_retries: int = 2, backoff: float = 0.5, headers: Mapping[str, str] | None = None,
                 http_client: httpx.Client | None = None):
        self._config = Config.create(base_url, api_key, timeout, max_retries, backoff, headers)
        self._http = http_client or httpx.Client()
        self._owns_http = http_client is None
        self._bind()

    def _bind(self) -> None:
        self.instances = Instances(self)
        self.nerfs = Nerfs(self)
        self.jobs = Jobs(self)

    @property
    def base_url(self) -> str:
        return self._config.base_url

    def with_options(self, *, timeout: Timeout | object = UNSET, max_retries: int | None = None) -> Client:
        """A client sharing this one's connections with another timeout or retry count."""
        clone = object.__new__(Client)
        clone._config = self._config.replace(timeout, max_retries)
        clone._http, clone._owns_http = self._http, False
        clone._bind()
        return clone

    def close(self) -> None:
        if self._owns_http:
            self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Client({self.base_url!r})"

    # -- sending ---------------------------------------------------------------------------------

    def _send(self, call: Call) -> httpx.Response:
        retries = 0
        while True:
            request = self._config.build(self._http, call)
            try:
                response = self._http.send(request, stream=call.stream)
            except httpx.TransportError as error:
                delay = self._config.retry_delay(call, retries, error=error)
                if delay is None:
                    raise transport_error(error, call.method, str(request.url)) from error
            else:
                if not response.is_error:
                    return response
                delay = self._config.retry_delay(call, retries, response=response)
                response.read()
                response.close()
                if delay is None:
                    raise api_error(response)
            time.sleep(delay)
            retries += 1

    def _run(self, call: Call[T]) -> T:
        return call.parse(self._send(call))

    # -- service ---------------------------------------------------------------------------------

    def health(self) -> Health:
        """``GET /healthz``: the process answers."""
        return self._run(calls.health())

    def ready(self) -> Ready:
        """``GET /readyz``: the bundle is loaded (a 503 while it loads is retried like any 503)."""
        return self._run(calls.ready())

    def model(self) -> ModelInfo:
        """``GET /v1/model``: the served bundle, code sizes, camera, limits."""
        return self._run(calls.model_info())

    def cache(self) -> CacheStats:
        """``GET /v1/cache``: the NeRF cache's hits, misses, evictions and bytes."""
        return self._run(calls.cache_stats())

    def metrics(self) -> str:
        """``GET /metrics``: Prometheus text."""
        return self._run(calls.metrics())

    def text_to_nerf(self, prompt: str) -> TextNerf:
        """``POST /v1/text-to-nerf``: the NeRF of a text prompt and the URL of a first view.
        Raises ``NotImplementedByServerError`` when the bundle has no query network."""
        return self._run(calls.text_to_nerf(prompt))

    def retrieve(self, image: ImageInput, k: int = 5) -> Retrieval:
        """``POST /v1/retrieve``: the ``k`` training instances nearest an image (path, bytes or binary file)."""
        return self._run(calls.retrieve(image, k))


class Instances:
    """``client.instances``: the bundle's training instances."""

    def __init__(self, client: Client):
        self._client = client

    def list(self, *, limit: int = 20, offset: int = 0) -> InstancePage:
        """One page of instances, from ``offset``."""
        return self._client._run(calls.list_instances(limit, offset))

    def iter_all(self, *, page_size: int = 100) -> Iterator[Instance]:
        """Every instance, fetching pages of ``page_size`` as it goes."""
        offset = 0
        while True:
            page = self.list(limit=page_size, offset=offset)
            yield from page.items
            offset = page.offset + len(page.items)
            if page.next is None or not page.items:
                return

    def get(self, instance: InstanceRef) -> Instance:
        return self._client._run(calls.get_instance(instance))


class Nerfs:
    """``client.nerfs``: create NeRFs, render them, export meshes."""

    def __init__(self, client: Client):
        self._client = client

    def create(self, *, instance: InstanceRef | None = None, codes: Codes | Mapping | Sequence | None = None,
               mix: Mix | Mapping | Sequence | None = None, interpolate: Interpolation | Mapping | Sequence | None = None) -> Nerf:
        """A NeRF from exactly one of: an ``instance`` id; ``codes`` (``Codes``, ``{"shape", "color"}``
        or ``(shape, color)``); ``mix`` (``(shape_instance, color_instance)``); ``interpolate``
        (``(a, b, t)``). Ids are content addresses: the same request always names the same NeRF."""
        return self._client._run(calls.create_nerf(instance, codes, mix, interpolate))

    def get(self, nerf: NerfRef) -> Nerf:
        return self._client._run(calls.get_nerf(nerf))

    def render(self, nerf: NerfRef, **options: Unpack[RenderOptions]) -> bytes:
        """A PNG of the NeRF (see ``RenderOptions``: azimuth, elevation, radius, fov, width, height,
        background, pose)."""
        return self._client._run(calls.render(nerf, options))

    def save_render(self, nerf: NerfRef, path: str | os.PathLike, **options: Unpack[RenderOptions]) -> Path:
        """``render()`` written to ``path``; returns the path."""
        return calls.write_file(path, self.render(nerf, **options))

    def turntable(self, nerf: NerfRef, **options: Unpack[TurntableOptions]) -> bytes:
        """An animated GIF circling the NeRF (see ``TurntableOptions``)."""
        return self._client._run(calls.turntable(nerf, options))

    def save_turntable(self, nerf: NerfRef, path: str | os.PathLike, **options: Unpack[TurntableOptions]) -> Path:
        return calls.write_file(path, self.turntable(nerf, **options))

    def mesh(self, nerf: NerfRef, **options: Unpack[MeshOptions]) -> bytes:
        """A mesh file (see ``MeshOptions``: format, resolution, target_faces, min_component, texture, texture_size)."""
        return self._client._run(calls.mesh(nerf, options))

    def save_mesh(self, nerf: NerfRef, path: str | os.PathLike, **options: Unpack[MeshOptions]) -> Path:
        """``mesh()`` written to ``path``; the format defaults to the file's suffix (.glb, .ply, .obj, .zip)."""
        return calls.write_file(path, self._client._run(calls.mesh(nerf, calls.mesh_options_for(path, options))))


class Jobs:
    """``client.jobs``: inversion jobs (a NeRF from photos, optimised on the server's workers)."""

    def __init__(self, client: Client):
        self._client = client

    def create_inversion(self, images: ImageInput | Sequence[ImageInput], *, poses: Sequence[Pose] | None = None,
                         masks: ImageInput | Sequence[ImageInput] | None = None,
                         options: InversionOptions | Mapping[str, Any] | None = None, idempotency_key: str | None = None) -> Job:
        """Submit images (paths, bytes or binary files) with one pose each and optional masks; answers
        the queued job. ``idempotency_key`` (default: a new UUID) makes retries return the same job."""
        return self._client._run(calls.create_inversion(images, poses, masks, options, idempotency_key))

    def get(self, job: JobRef) -> Job:
        return self._client._run(calls.get_job(job))

    def cancel(self, job: JobRef) -> Job:
        """Cancel a job (queued: at once; running: within a step). ``ConflictError`` if it already finished."""
        return self._client._run(calls.cancel_job(job))

    def list(self, *, status: JobStatus | None = None, limit: int = 20, cursor: str | None = None) -> JobList:
        """One page of jobs, newest first; pass the page's ``next`` as ``cursor`` for the following one."""
        return self._client._run(calls.list_jobs(status, limit, cursor))

    def iter_all(self, *, status: JobStatus | None = None, page_size: int = 100) -> Iterator[Job]:
        """Every job (with ``status``), newest first, fetching pages as it goes."""
        cursor = None
        while True:
            page = self.list(status=status, limit=page_size, cursor=cursor)
            yield from page.items
            if page.next is None:
                return
            cursor = page.next

    def wait(self, job: JobRef, *, timeout: float | None = None, poll_interval: float = 0.5,
             on_progress: Callable[[Job], Any] | None = None) -> Job:
        """Poll until the job succeeds and return it; ``on_progress(job)`` is called whenever its status
        or progress changes. Raises ``JobFailedError``, ``JobCanceledError`` or, after ``timeout``
        seconds, ``JobTimeoutError``."""
        watch = calls.JobWatch(calls.job_id(job), timeout, poll_interval, on_progress)
        while not watch.finished(self.get(watch.job)):
            time.sleep(watch.pause())
        return watch.seen

    def events(self, job: JobRef) -> Iterator[JobEvent]:
        """The job's server-sent events: the job each time it changes, ending after its final status."""
        response = self._client._send(calls.job_events(job))
        decoder = SSEDecoder()
        try:
            for line in response.iter_lines():
                event = decoder.decode(line)
                if event is not None and (parsed := calls.job_event(event)) is not None:
                    yield parsed
        except httpx.TransportError as error:
            raise transport_error(error, "GET", str(response.request.url)) from error
        finally:
            response.close()
