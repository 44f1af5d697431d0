"""What each SDK method sends and how its answer is read, shared by ``Client`` and ``AsyncClient``.

A ``Call`` is one HTTP exchange described as data: method, path, query, body, whether repeating it
is safe, and the parser of a successful answer. The clients only send calls (with retries) and
sleep; everything that knows the API lives here, once. Arguments are checked before anything is
sent, so a typo raises ``TypeError``/``ValueError`` at once instead of a round trip.
"""

from __future__ import annotations

import json
import mimetypes
import os
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Generic, Literal, TypedDict, TypeVar
from urllib.parse import quote

import httpx
from pydantic import BaseModel

from hypnerf_client._sse import ServerSentEvent
from hypnerf_client.errors import JobCanceledError, JobFailedError, JobTimeoutError
from hypnerf_client.types import (CacheStats, Codes, Health, Instance, InstancePage, Interpolation, InversionOptions, Job, JobEvent,
                                  JobList, JobResult, MatrixPose, Mix, ModelInfo, Nerf, OrbitPose, Ready, Retrieval, TextNerf)

T = TypeVar("T")
M = TypeVar("M", bound=BaseModel)

NerfRef = str | Nerf | TextNerf | JobResult
"""A NeRF: its id, or a result that names one (``Nerf``, ``TextNerf``, a job's ``JobResult``)."""
JobRef = str | Job
InstanceRef = str | Instance
ImageInput = str | os.PathLike | bytes | IO[bytes]
"""An image to upload: a file path, the encoded bytes (PNG, JPEG or WebP), or a binary file object."""
Pose = Sequence[Sequence[float]] | Sequence[float] | Mapping[str, Any] | OrbitPose | MatrixPose
"""A camera: a 4x4 camera-to-world matrix (nested or flat, numpy arrays too), ``{"azimuth",
"elevation", "radius", "fov"}``, ``{"c2w", "fov"}``, or an ``OrbitPose``/``MatrixPose``."""
Background = str | Sequence[int]
"""``"ffffff"`` (``#`` optional), ``"transparent"`` (RGBA PNG) or an ``(r, g, b)`` of 0-255."""


class ViewOptions(TypedDict, total=False):
    """An orbit camera: ``azimuth`` degrees from +X towards +Y, ``elevation`` degrees above the
    ground plane (+Z up), ``radius`` from the scene centre, horizontal ``fov`` in degrees. Left
    out, the server's defaults apply (``ModelInfo.camera``)."""

    azimuth: float
    elevation: float
    radius: float
    fov: float


class RenderOptions(ViewOptions, total=False):
    """A render: the orbit, or ``pose`` (a 4x4 camera-to-world matrix) instead; size in pixels;
    ``background``."""

    width: int
    height: int
    background: Background
    pose: Pose


class TurntableOptions(ViewOptions, total=False):
    """A turntable: ``frames`` around the full circle starting at ``azimuth``, ``fps``, frame size,
    ``background`` and ``format`` (``gif``, or ``mp4`` where the server has imageio's ffmpeg plugin)."""

    frames: int
    fps: float
    width: int
    height: int
    background: Background
    format: Literal["gif", "mp4"]


class MeshOptions(TypedDict, total=False):
    """A mesh: ``format`` glb (Y-up) / ply / obj (Z-up), marching-cubes ``resolution``,
    ``target_faces`` (decimation), ``min_component`` (drop small pieces), ``texture`` ``vertex``
    colours or a ``uv`` atlas with a baked texture of ``texture_size`` pixels."""

    format: Literal["glb", "ply", "obj"]
    resolution: int
    target_faces: int
    min_component: float
    texture: Literal["vertex", "uv"]
    texture_size: int


@dataclass(frozen=True)
class Call(Generic[T]):
    """One HTTP exchange: what to send, whether it may be repeated, how to read a success."""

    method: str
    path: str
    parse: Callable[[httpx.Response], T]
    params: dict[str, Any] | None = None
    json: Any = None
    data: dict[str, str] | None = None
    files: list[tuple[str, tuple[str, bytes, str]]] | None = None
    headers: dict[str, str] = field(default_factory=dict)
    idempotent: bool = True
    stream: bool = False


def _model(cls: type[M]) -> Callable[[httpx.Response], M]:
    return lambda response: cls.model_validate_json(response.content)


def _content(response: httpx.Response) -> bytes:
    return response.content


def _segment(value: str) -> str:
    """A path segment: ids are quoted so that no value can reach another route."""
    if not isinstance(value, str) or not value:
        raise TypeError(f"expected a non-empty id string, got {value!r}")
    return quote(value, safe="")


def nerf_id(nerf: NerfRef) -> str:
    if isinstance(nerf, Nerf):
        return nerf.id
    if isinstance(nerf, TextNerf):
        return nerf.nerf.id
    if isinstance(nerf, JobResult):
        return nerf.nerf_id
    return nerf


def job_id(job: JobRef) -> str:
    return job.id if isinstance(job, Job) else job


def instance_id(instance: InstanceRef) -> str:
    return instance.id if isinstance(instance, Instance) else instance


def _plain(value: Any) -> Any:
    """numpy arrays and scalars (anything with ``tolist``) as plain lists and numbers."""
    return value.tolist() if hasattr(value, "tolist") else value


def _options(given: Mapping[str, Any], allowed: type, what: str) -> dict[str, Any]:
    """The options of a TypedDict that were given (``None`` means the server's default)."""
    unknown = sorted(set(given) - set(allowed.__optional_keys__))
    if unknown:
        raise TypeError(f"{what}() got unexpected option(s) {unknown}; it takes {sorted(allowed.__optional_keys__)}")
    return {key: value for key, value in given.items() if value is not None}


def _background(value: Background) -> str:
    if isinstance(value, str):
        return value.removeprefix("#")
    rgb = [int(c) for c in _plain(value)]
    if len(rgb) != 3 or not all(0 <= c <= 255 for c in rgb):
        raise ValueError(f"background must be a hex colour, 'transparent' or (r, g, b) in 0..255, got {value!r}")
    return "".join(f"{c:02x}" for c in rgb)


def _flat_pose(pose: Pose) -> str:
    """A 4x4 camera-to-world matrix as the 16 comma-separated numbers of the render query."""
    if isinstance(pose, MatrixPose):
        pose = pose.c2w
    elif isinstance(pose, Mapping) and "c2w" in pose:
        pose = pose["c2w"]
    rows = _plain(pose)
    values = [float(_plain(v)) for row in rows for v in (row if isinstance(row, Sequence) else [row])]
    if len(values) != 16:
        raise ValueError(f"pose must be a 4x4 camera-to-world matrix (16 numbers), got {len(values)}")
    return ",".join(repr(v) for v in values)


def _view_params(options: dict[str, Any]) -> dict[str, Any]:
    if "background" in options:
        options["background"] = _background(options["background"])
    if "pose" in options:
        options["pose"] = _flat_pose(options["pose"])
    return options


# -- health, model, instances ----------------------------------------------------------------------


def health() -> Call[Health]:
    return Call("GET", "/healthz", _model(Health))


def ready() -> Call[Ready]:
    return Call("GET", "/readyz", _model(Ready))


def model_info() -> Call[ModelInfo]:
    return Call("GET", "/v1/model", _model(ModelInfo))


def cache_stats() -> Call[CacheStats]:
    return Call("GET", "/v1/cache", _model(CacheStats))


def metrics() -> Call[str]:
    return Call("GET", "/metrics", lambda response: response.text)


def list_instances(limit: int, offset: int) -> Call[InstancePage]:
    return Call("GET", "/v1/instances", _model(InstancePage), params={"limit": limit, "offset": offset})


def get_instance(instance: InstanceRef) -> Call[Instance]:
    return Call("GET", f"/v1/instances/{_segment(instance_id(instance))}", _model(Instance))


# -- NeRFs ------------------------------------------------------------------------------------------


def _pair(value: Any, cls: type[M], names: tuple[str, ...]) -> M:
    """A request part from the model itself, a dict, or a tuple in field order."""
    if isinstance(value, cls):
        return value
    if isinstance(value, Mapping):
        return cls.model_validate({k: instance_id(v) if isinstance(v, Instance) else _plain(v) for k, v in value.items()})
    if isinstance(value, Sequence) and not isinstance(value, str) and len(value) <= len(names):
        return cls.model_validate({k: instance_id(v) if isinstance(v, Instance) else _plain(v) for k, v in zip(names, value)})
    raise TypeError(f"expected a {cls.__name__}, a dict with {list(names)} or a tuple of them, got {value!r}")


def create_nerf(instance: InstanceRef | None = None, codes: Codes | Mapping | Sequence | None = None,
                mix: Mix | Mapping | Sequence | None = None, interpolate: Interpolation | Mapping | Sequence | None = None) -> Call[Nerf]:
    given = {name: value for name, value in (("instance", instance), ("codes", codes), ("mix", mix), ("interpolate", interpolate))
             if value is not None}
    if len(given) != 1:
        raise TypeError(f"give exactly one of instance=, codes=, mix= or interpolate= (got {sorted(given) or 'none'})")
    kind, value = next(iter(given.items()))
    if kind == "instance":
        body: Any = instance_id(value)
    else:
        cls, names = {"codes": (Codes, ("shape", "color")), "mix": (Mix, ("shape", "color")),
                      "interpolate": (Interpolation, ("a", "b", "t"))}[kind]
        body = _pair(value, cls, names).model_dump(exclude_none=True)
    # creation is content-addressed: repeating it names (or regenerates) the same NeRF
    return Call("POST", "/v1/nerfs", _model(Nerf), json={kind: body})


def get_nerf(nerf: NerfRef) -> Call[Nerf]:
    return Call("GET", f"/v1/nerfs/{_segment(nerf_id(nerf))}", _model(Nerf))


def render(nerf: NerfRef, options: Mapping[str, Any]) -> Call[bytes]:
    params = _view_params(_options(options, RenderOptions, "render"))
    return Call("GET", f"/v1/nerfs/{_segment(nerf_id(nerf))}/render", _content, params=params)


def turntable(nerf: NerfRef, options: Mapping[str, Any]) -> Call[bytes]:
    params = _view_params(_options(options, TurntableOptions, "turntable"))
    return Call("GET", f"/v1/nerfs/{_segment(nerf_id(nerf))}/turntable", _content, params=params)


def mesh(nerf: NerfRef, options: Mapping[str, Any]) -> Call[bytes]:
    params = _options(options, MeshOptions, "mesh")
    return Call("GET", f"/v1/nerfs/{_segment(nerf_id(nerf))}/mesh", _content, params=params)


MESH_SUFFIXES = {".glb": "glb", ".ply": "ply", ".obj": "obj", ".zip": "obj"}


def mesh_options_for(path: str | os.PathLike, options: Mapping[str, Any]) -> dict[str, Any]:
    """``options`` with the format taken from the file name when not given (``.zip``: OBJ with its
    material and texture, for ``texture="uv"``)."""
    chosen = dict(options)
    if chosen.get("format") is None:
        suffix = Path(path).suffix.lower()
        if suffix not in MESH_SUFFIXES:
            raise ValueError(f"cannot tell the mesh format from {os.fspath(path)!r}; name it .glb, .ply, .obj or .zip, or pass format=")
        chosen["format"] = MESH_SUFFIXES[suffix]
    return chosen


def write_file(path: str | os.PathLike, data: bytes) -> Path:
    """A downloaded render or mesh written to ``path`` (its folder must exist)."""
    target = Path(path)
    target.write_bytes(data)
    return target


def text_to_nerf(prompt: str) -> Call[TextNerf]:
    if not isinstance(prompt, str) or not prompt.strip():
        raise ValueError("prompt must be a non-empty description, e.g. 'a red wooden chair'")
    return Call("POST", "/v1/text-to-nerf", _model(TextNerf), json={"text": prompt})


# -- uploads ----------------------------------------------------------------------------------------

_MAGIC = ((b"\x89PNG\r\n\x1a\n", "image/png"), (b"\xff\xd8\xff", "image/jpeg"))


def _media_type(data: bytes, name: str) -> str:
    for magic, media in _MAGIC:
        if data.startswith(magic):
            return media
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "image/webp"
    return mimetypes.guess_type(name)[0] or "application/octet-stream"


def upload(field_name: str, image: ImageInput, default_name: str) -> tuple[str, tuple[str, bytes, str]]:
    """A multipart file part, read into memory so that a retry can send it again."""
    if isinstance(image, (bytes, bytearray, memoryview)):
        data, name = bytes(image), default_name
    elif isinstance(image, (str, os.PathLike)):
        path = Path(image)
        data, name = path.read_bytes(), path.name
    elif hasattr(image, "read"):
        data = image.read()
        if not isinstance(data, bytes):
            raise TypeError(f"{field_name}: open image files in binary mode ('rb')")
        given = getattr(image, "name", None)
        name = Path(given).name if isinstance(given, str) else default_name
    else:
        raise TypeError(f"{field_name}: expected a path, bytes or a binary file, got {type(image).__name__}")
    return field_name, (name, data, _media_type(data, name))


def _uploads(field_name: str, images: ImageInput | Sequence[ImageInput]) -> list[tuple[str, tuple[str, bytes, str]]]:
    if isinstance(images, (str, os.PathLike, bytes, bytearray, memoryview)) or hasattr(images, "read"):
        images = [images]
    return [upload(field_name, image, f"{field_name}{i}.png") for i, image in enumerate(images)]


def retrieve(image: ImageInput, k: int) -> Call[Retrieval]:
    # retrieval only reads: repeating it is safe
    return Call("POST", "/v1/retrieve", _model(Retrieval), data={"k": str(int(k))}, files=[upload("image", image, "image.png")])


# -- jobs ---------------------------------------------------------------------------------------------


def _pose_part(pose: Pose) -> Any:
    if isinstance(pose, (OrbitPose, MatrixPose)):
        return pose.model_dump(exclude_none=True)
    if isinstance(pose, Mapping):
        return {key: _plain(value) for key, value in pose.items()}
    matrix = _plain(pose)
    if len(matrix) == 16 and not isinstance(matrix[0], Sequence):
        matrix = [list(matrix[i:i + 4]) for i in range(0, 16, 4)]
    return [[float(_plain(v)) for v in row] for row in matrix]


def create_inversion(images: ImageInput | Sequence[ImageInput], poses: Sequence[Pose] | None,
                     masks: ImageInput | Sequence[ImageInput] | None, options: InversionOptions | Mapping[str, Any] | None,
                     idempotency_key: str | None) -> Call[Job]:
    files = _uploads("images", images)
    if not files:
        raise ValueError("give at least one image")
    if masks is not None:
        files += _uploads("masks", masks)
    data: dict[str, str] = {}
    if poses is not None:
        data["poses"] = json.dumps([_pose_part(pose) for pose in _plain(poses)])
    if options is not None:
        chosen = options if isinstance(options, InversionOptions) else InversionOptions.model_validate(dict(options))
        data["options"] = chosen.model_dump_json(exclude_none=True)
    # the key makes a repeated submission (a retry after a lost answer) return the same job
    key = idempotency_key or uuid.uuid4().hex
    return Call("POST", "/v1/jobs/inversions", _model(Job), data=data, files=files, headers={"Idempotency-Key": key})


def get_job(job: JobRef) -> Call[Job]:
    return Call("GET", f"/v1/jobs/{_segment(job_id(job))}", _model(Job))


def cancel_job(job: JobRef) -> Call[Job]:
    # canceling is idempotent: canceling a canceled job answers it unchanged
    return Call("POST", f"/v1/jobs/{_segment(job_id(job))}/cancel", _model(Job))


def list_jobs(status: str | None, limit: int, cursor: str | None) -> Call[JobList]:
    params = {key: value for key, value in (("status", status), ("limit", limit), ("cursor", cursor)) if value is not None}
    return Call("GET", "/v1/jobs", _model(JobList), params=params)


def job_events(job: JobRef) -> Call[None]:
    return Call("GET", f"/v1/jobs/{_segment(job_id(job))}/events", lambda response: None, headers={"Accept": "text/event-stream"},
                stream=True)


def job_event(event: ServerSentEvent) -> JobEvent | None:
    """A ``job`` server-sent event as a ``JobEvent`` (other events are not the SDK's)."""
    if event.event != "job":
        return None
    return JobEvent(id=event.id, event=event.event, job=Job.model_validate_json(event.data))


class JobWatch:
    """What ``jobs.wait()`` does with each job it polls: report changes, stop at the end, keep time."""

    def __init__(self, job: str, timeout: float | None, poll_interval: float, on_progress: Callable[[Job], Any] | None):
        if poll_interval <= 0:
            raise ValueError(f"poll_interval must be positive seconds, got {poll_interval}")
        self.job = job
        self.timeout = timeout
        self.poll_interval = poll_interval
        self.on_progress = on_progress
        self.deadline = None if timeout is None else time.monotonic() + timeout
        self.last: tuple | None = None
        self.seen: Job | None = None

    def finished(self, job: Job) -> bool:
        """True once ``job`` succeeded; raises when it failed or was canceled."""
        self.seen = job
        state = (job.status, job.progress.model_dump_json() if job.progress else None)
        if state != self.last:
            self.last = state
            if self.on_progress is not None:
                self.on_progress(job)
        if job.status == "succeeded":
            return True
        if job.status == "failed":
            reason = f"{job.error.title}: {job.error.detail}" if job.error else "no reason given"
            raise JobFailedError(f"job {job.id} failed after {job.attempts} attempt(s): {reason}", job)
        if job.status == "canceled":
            raise JobCanceledError(f"job {job.id} was canceled", job)
        return False

    def pause(self) -> float:
        """Seconds to sleep before the next poll; raises once the timeout has passed."""
        if self.deadline is None:
            return self.poll_interval
        left = self.deadline - time.monotonic()
        if left <= 0:
            status = self.seen.status if self.seen else "unknown"
            raise JobTimeoutError(f"job {self.job} is still {status} after {self.timeout:g} s; it keeps running on the server "
                                  "(wait again, or cancel it)", self.seen)
        return min(self.poll_interval, left)
