"""Generated NeRFs: create (instance, codes, mix, interpolation), describe, render, turntable, mesh."""

from __future__ import annotations

import importlib.util
import io
from typing import Annotated

import imageio.v3 as iio
import numpy as np
from fastapi import APIRouter, Body, Path, Query, Response
from PIL import Image

from service import meshing
from service.cache import NerfEntry
from service.poses import PoseError, intrinsics, orbit_pose, parse_pose
from service.problems import ProblemError
from service.resident import Resident
from service.routers.deps import ResidentDep, invalid
from service.schemas.common import NERF_ID_PATTERN, PROBLEM_RESPONSES
from service.schemas.nerfs import (
    CREATE_EXAMPLES,
    Codes,
    FromCodes,
    FromInstance,
    FromMix,
    GridInfo,
    MeshQuery,
    Nerf,
    NerfCreate,
    NerfLinks,
    Orbit,
    RenderQuery,
    TurntableQuery,
)

router = APIRouter(prefix="/v1/nerfs", tags=["nerfs"],
                   responses={code: PROBLEM_RESPONSES[code] for code in (404, 422, 429, 503)})

NerfId = Annotated[str, Path(pattern=NERF_ID_PATTERN, description="a NeRF id from POST /v1/nerfs (64 hex digits)")]
# a content-addressed NeRF never changes, so its renders and meshes never do either
IMMUTABLE = {"Cache-Control": "public, max-age=86400, immutable"}
PNG = {"content": {"image/png": {}}, "description": "the rendered view"}


def source_codes(body, resident: Resident) -> tuple[np.ndarray, np.ndarray]:
    """The shape and colour codes a creation request names."""
    if isinstance(body, FromInstance):
        return resident.instance_codes(resident.instance_number(body.instance, "instance"))
    if isinstance(body, FromCodes):
        return resident.check_codes(body.codes.shape, body.codes.color)
    if isinstance(body, FromMix):
        shape, _ = resident.instance_codes(resident.instance_number(body.mix.shape, "mix.shape"))
        _, color = resident.instance_codes(resident.instance_number(body.mix.color, "mix.color"))
        return shape, color
    a = resident.instance_codes(resident.instance_number(body.interpolate.a, "interpolate.a"))
    b = resident.instance_codes(resident.instance_number(body.interpolate.b, "interpolate.b"))
    t = np.float32(body.interpolate.t)
    return (1 - t) * a[0] + t * b[0], (1 - t) * a[1] + t * b[1]


def nerf_view(nerf_id: str, entry: NerfEntry, cached: bool) -> Nerf:
    box = entry.grid.tight_box()
    base = f"/v1/nerfs/{nerf_id}"
    meta = entry.meta
    return Nerf(
        id=nerf_id, cached=cached, source=meta.get("source", {}), created_at=meta.get("created_at", ""), bundle=meta.get("bundle", ""),
        codes=Codes(**meta["codes"]) if "codes" in meta else None,
        grid=GridInfo(resolution=entry.grid.resolution, occupied_fraction=round(entry.grid.fraction, 6),
                      box=[box[0].tolist(), box[1].tolist()] if box is not None else None),
        bytes=entry.nbytes,
        links=NerfLinks(self=base, render=f"{base}/render", turntable=f"{base}/turntable", mesh=f"{base}/mesh"),
    )


async def create_from_codes(resident: Resident, shape: np.ndarray, color: np.ndarray, source: dict, response: Response) -> Nerf:
    """Create (or find) the NeRF of these codes; 201 when generated now, 200 when it was cached."""
    nerf_id, entry, cached = await resident.create(shape, color, source)
    response.status_code = 200 if cached else 201
    response.headers["Location"] = f"/v1/nerfs/{nerf_id}"
    return nerf_view(nerf_id, entry, cached)


@router.post("", response_model=Nerf, status_code=201, summary="create a NeRF (or find it: ids are content addresses)",
             responses={200: {"description": "the NeRF already existed", "model": Nerf}})
async def create_nerf(body: Annotated[NerfCreate, Body(openapi_examples=CREATE_EXAMPLES)], response: Response, resident: ResidentDep) -> Nerf:
    shape, color = source_codes(body, resident)
    return await create_from_codes(resident, shape, color, body.model_dump(), response)


@router.get("/{nerf_id}", response_model=Nerf, summary="a NeRF's source, codes and occupancy")
async def get_nerf(nerf_id: NerfId, resident: ResidentDep) -> Nerf:
    return nerf_view(nerf_id, await resident.entry(nerf_id), True)


def _check_side(name: str, value: int, limit: int, setting: str) -> None:
    if value > limit:
        raise invalid(name, "query", f"at most {limit} pixels (HYPNERF_LIMITS__{setting}), got {value}")


def _camera_pose(resident: Resident, orbit: Orbit, pose: str | None = None) -> np.ndarray:
    scene = resident.bundle.scene
    try:
        if pose is not None:
            return parse_pose(pose, scene)
        return orbit_pose(scene, orbit.azimuth, orbit.elevation, orbit.radius or resident.default_radius)
    except PoseError as error:
        raise invalid("pose" if pose is not None else "radius", "query", str(error), "Invalid camera") from None


def _background(text: str) -> tuple[float, float, float] | None:
    if text == "transparent":
        return None
    return tuple(int(text[i:i + 2], 16) / 255.0 for i in (0, 2, 4))


def _png(image: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG", compress_level=3)
    return buffer.getvalue()


@router.get("/{nerf_id}/render", response_class=Response, responses={200: PNG},
            summary="a PNG from an orbit camera (azimuth, elevation, radius, fov) or a 4x4 camera-to-world pose")
async def render(nerf_id: NerfId, query: Annotated[RenderQuery, Query()], resident: ResidentDep) -> Response:
    limits = resident.settings.limits
    _check_side("width", query.width, limits.max_render_side, "MAX_RENDER_SIDE")
    _check_side("height", query.height, limits.max_render_side, "MAX_RENDER_SIDE")
    c2w = _camera_pose(resident, query, query.pose)
    camera = intrinsics(query.width, query.height, query.fov or resident.default_fov)
    background = _background(query.background)
    entry = await resident.entry(nerf_id)
    data = await resident.compute("render", lambda: _png(resident.render(entry, c2w, camera, background)))
    return Response(data, media_type="image/png", headers=IMMUTABLE)


def _turntable(resident: Resident, entry: NerfEntry, query: TurntableQuery) -> bytes:
    camera = intrinsics(query.width, query.height, query.fov or resident.default_fov)
    background = _background(query.background)
    radius = query.radius or resident.default_radius
    frames = [resident.render(entry, orbit_pose(resident.bundle.scene, query.azimuth + 360.0 * i / query.frames, query.elevation, radius),
                              camera, background) for i in range(query.frames)]
    if query.format == "gif":
        return iio.imwrite("<bytes>", np.stack(frames), extension=".gif", duration=1000.0 / query.fps, loop=0)
    return iio.imwrite("<bytes>", np.stack(frames), extension=".mp4", plugin="FFMPEG", fps=query.fps, codec="libx264")


@router.get("/{nerf_id}/turntable", response_class=Response,
            responses={200: {"content": {"image/gif": {}, "video/mp4": {}}, "description": "an animated GIF (or MP4) circling the NeRF"}},
            summary="an animated GIF of the NeRF turning (MP4 where imageio's ffmpeg plugin is installed)")
async def turntable(nerf_id: NerfId, query: Annotated[TurntableQuery, Query()], resident: ResidentDep) -> Response:
    limits = resident.settings.limits
    _check_side("width", query.width, limits.max_turntable_side, "MAX_TURNTABLE_SIDE")
    _check_side("height", query.height, limits.max_turntable_side, "MAX_TURNTABLE_SIDE")
    if query.frames > limits.max_turntable_frames:
        raise invalid("frames", "query", f"at most {limits.max_turntable_frames} frames (HYPNERF_LIMITS__MAX_TURNTABLE_FRAMES), got {query.frames}")
    if query.format == "mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise invalid("format", "query", "MP4 needs imageio's ffmpeg plugin (pip install imageio-ffmpeg), which this server lacks; use format=gif",
                      "MP4 unavailable")
    _camera_pose(resident, query)  # the orbit must keep the camera outside the scene box
    entry = await resident.entry(nerf_id)
    data = await resident.compute("turntable", _turntable, resident, entry, query)
    media = "image/gif" if query.format == "gif" else "video/mp4"
    return Response(data, media_type=media, headers={**IMMUTABLE, "Content-Disposition": f'inline; filename="{nerf_id[:12]}.{query.format}"'})


def _empty_mesh() -> ProblemError:
    return ProblemError(422, "Empty mesh", "this NeRF has no surface above the density threshold (its occupancy grid is empty "
                        "or too faint), or none is left at this face budget; nothing to export", kind="empty-mesh")


def build_mesh(resident: Resident, entry: NerfEntry, query: MeshQuery) -> tuple[bytes, str, str]:
    bundle = resident.bundle
    mesh = meshing.nerf_geometry(entry.params, bundle.field, entry.grid, bundle.scene, query.resolution, query.min_component)
    target = query.target_faces or (meshing.DEFAULT_UV_FACES if query.texture == "uv" else None)
    if target is not None and not mesh.is_empty:
        mesh = meshing.decimate(mesh, target)
    if mesh.is_empty:
        raise _empty_mesh()
    if query.texture == "uv":
        mesh = meshing.bake_uv_texture(mesh, entry.params, bundle.field, bundle.scene, query.texture_size)
    else:
        mesh = meshing.color_vertices(mesh, entry.params, bundle.field, bundle.scene)
    return meshing.encode(mesh, query.format, query.texture)


@router.get("/{nerf_id}/mesh", response_class=Response,
            responses={200: {"content": {t: {} for t in meshing.MEDIA_TYPES.values()}, "description": "the mesh file"}},
            summary="a marching-cubes mesh (GLB Y-up; PLY/OBJ Z-up) with vertex colours or a baked UV texture")
async def mesh(nerf_id: NerfId, query: Annotated[MeshQuery, Query()], resident: ResidentDep) -> Response:
    limits = resident.settings.limits
    if query.resolution > limits.max_mesh_resolution:
        raise invalid("resolution", "query", f"at most {limits.max_mesh_resolution} (HYPNERF_LIMITS__MAX_MESH_RESOLUTION), got {query.resolution}")
    if query.texture == "uv" and query.texture_size > limits.max_texture_size:
        raise invalid("texture_size", "query", f"at most {limits.max_texture_size} (HYPNERF_LIMITS__MAX_TEXTURE_SIZE), got {query.texture_size}")
    if query.texture == "uv" and query.format == "ply":
        raise invalid("texture", "query", "PLY cannot carry a texture image; use format=glb or format=obj (a zip), or texture=vertex")
    entry = await resident.entry(nerf_id)
    data, media, extension = await resident.compute("mesh", build_mesh, resident, entry, query)
    return Response(data, media_type=media, headers={**IMMUTABLE, "Content-Disposition": f'attachment; filename="{nerf_id[:12]}.{extension}"'})
