"""Creating NeRFs (from an instance, codes, a shape/colour mix or an interpolation), describing
them, and the query parameters of renders, turntables and meshes."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag

from service.schemas.common import FiniteFloat

INSTANCE_ID = Field(min_length=1, max_length=256, description="an instance id from GET /v1/instances")


class _Source(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FromInstance(_Source):
    """A training instance's own shape and colour codes."""

    instance: Annotated[str, INSTANCE_ID]


class Codes(_Source):
    shape: list[FiniteFloat] = Field(description="shape code, `codes.shape` long (see GET /v1/model)", max_length=65536)
    color: list[FiniteFloat] = Field(description="colour code, `codes.color` long", max_length=65536)


class FromCodes(_Source):
    """Explicit codes (finite numbers, the lengths GET /v1/model gives)."""

    codes: Codes


class Mix(_Source):
    shape: Annotated[str, INSTANCE_ID]
    color: Annotated[str, INSTANCE_ID]


class FromMix(_Source):
    """One instance's shape code with another's colour code."""

    mix: Mix


class Interpolation(_Source):
    a: Annotated[str, INSTANCE_ID]
    b: Annotated[str, INSTANCE_ID]
    t: float = Field(0.5, ge=0.0, le=1.0, description="0 gives a, 1 gives b; both codes are interpolated linearly")


class FromInterpolation(_Source):
    """Codes linearly interpolated between two instances."""

    interpolate: Interpolation


SOURCES = ("instance", "codes", "mix", "interpolate")


def _source_kind(value: Any) -> str | None:
    """Which source a request body gives: the one of ``SOURCES`` among its keys (None unless exactly one)."""
    if isinstance(value, dict):
        present = [key for key in SOURCES if key in value]
        return present[0] if len(present) == 1 else None
    return next((key for key in SOURCES if hasattr(value, key)), None)


NerfCreate = Annotated[
    Annotated[FromInstance, Tag("instance")] | Annotated[FromCodes, Tag("codes")] | Annotated[FromMix, Tag("mix")] | Annotated[FromInterpolation, Tag("interpolate")],
    Discriminator(_source_kind, custom_error_type="nerf_source",
                  custom_error_message="give exactly one of 'instance', 'codes', 'mix' or 'interpolate'",
                  custom_error_context={"discriminator": "instance | codes | mix | interpolate"}),
]

CREATE_EXAMPLES = {
    "instance": {"summary": "a training instance", "value": {"instance": "sh3d-blendswap-cc-0-antiquechair"}},
    "mix": {"summary": "shape of one instance, colour of another",
            "value": {"mix": {"shape": "sh3d-blendswap-cc-0-antiquechair", "color": "sh3d-blendswap-cc-0-antiquechair-v1"}}},
    "interpolate": {"summary": "halfway between two instances",
                    "value": {"interpolate": {"a": "sh3d-blendswap-cc-0-antiquechair", "b": "sh3d-blendswap-cc-0-antiquechair-v2", "t": 0.5}}},
    "codes": {"summary": "explicit codes, as long as GET /v1/model's `codes` says (128 each in the demo bundle)",
              "value": {"codes": {"shape": [0.0] * 128, "color": [0.0] * 128}}},
}


class GridInfo(BaseModel):
    resolution: int
    occupied_fraction: float
    box: list[list[float]] | None = Field(description="tight box of the occupied cells (world units), null if empty")


class NerfLinks(BaseModel):
    self: str
    render: str
    turntable: str
    mesh: str


class Nerf(BaseModel):
    id: str = Field(description="content address: sha256 of the bundle digest and the codes")
    cached: bool = Field(description="true when the NeRF was already in the cache (no hypernetwork run)")
    source: dict = Field(description="what the NeRF was made from, as requested")
    created_at: str
    bundle: str = Field(description="digest of the bundle that generated it")
    codes: Codes | None = Field(None, description="the shape and colour codes it was generated from")
    grid: GridInfo
    bytes: int = Field(description="size of its parameters and occupancy grid")
    links: NerfLinks


_BACKGROUND = Field("ffffff", pattern=r"^([0-9a-fA-F]{6}|transparent)$",
                    description="RGB hex without '#', e.g. ffffff, or `transparent` for an RGBA PNG")


class Orbit(BaseModel):
    """A look-at camera on a sphere around the scene centre, +Z up."""

    azimuth: FiniteFloat = Field(30.0, description="degrees from +X towards +Y around +Z")
    elevation: float = Field(25.0, ge=-89.0, le=89.0, allow_inf_nan=False, description="degrees above the XY plane")
    radius: float | None = Field(None, gt=0.0, allow_inf_nan=False, description="distance from the scene centre (world units); default GET /v1/model camera.radius")
    fov: float | None = Field(None, gt=1.0, lt=170.0, allow_inf_nan=False, description="horizontal field of view in degrees; default the training camera's")


class RenderQuery(Orbit):
    width: int = Field(256, ge=1, description="pixels (at most limits.max_render_side)")
    height: int = Field(256, ge=1, description="pixels (at most limits.max_render_side)")
    background: str = _BACKGROUND
    pose: str | None = Field(None, max_length=2000, description=(
        "instead of the orbit: 16 comma-separated numbers, a row-major 4x4 camera-to-world matrix in the OpenGL "
        "convention (camera looks down its -Z, +Y up); rotation orthonormal, bottom row 0,0,0,1, camera outside the scene box"))


class TurntableQuery(Orbit):
    frames: int = Field(36, ge=1, description="views around the full circle (at most limits.max_turntable_frames)")
    fps: float = Field(12.0, ge=1.0, le=50.0)
    width: int = Field(192, ge=1, description="pixels (at most limits.max_turntable_side)")
    height: int = Field(192, ge=1)
    background: str = Field("ffffff", pattern=r"^[0-9a-fA-F]{6}$", description="RGB hex without '#'")
    format: Literal["gif", "mp4"] = Field("gif", description="gif always; mp4 only where imageio's ffmpeg plugin is installed")


class MeshQuery(BaseModel):
    format: Literal["glb", "ply", "obj"] = Field("glb", description="glb is Y-up (glTF); ply and obj keep the Z-up world")
    resolution: int = Field(128, ge=16, description="marching-cubes cells per axis over the occupied box (at most limits.max_mesh_resolution)")
    target_faces: int | None = Field(None, ge=4, le=10_000_000, description="decimate to at most this many faces; default: none for vertex colours, 10000 for uv (xatlas time grows faster than the face count)")
    min_component: float = Field(0.02, ge=0.0, le=1.0, description=(
        "drop connected pieces with less area than this fraction of the largest piece's (NeRF floaters); 0 keeps everything"))
    texture: Literal["vertex", "uv"] = Field("vertex", description="vertex colours, or a UV atlas (xatlas) with a baked texture (glb, or obj as a zip)")
    texture_size: int = Field(1024, ge=64, description="baked texture side in pixels (texture=uv; at most limits.max_texture_size)")
