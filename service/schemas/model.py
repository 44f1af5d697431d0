"""What the server serves: the bundle, its components and configs, the limits; the NeRF cache."""

from __future__ import annotations

from pydantic import BaseModel, Field

from service.settings import Limits


class BundleInfo(BaseModel):
    digest: str = Field(description="sha256 of the bundle's manifest: part of every NeRF id")
    format: int
    created: str | None = None
    components: list[str] = Field(description="the parts the bundle holds: hypernet, and optionally query, denoiser")


class CodeDims(BaseModel):
    shape: int
    color: int


class CameraInfo(BaseModel):
    width: int
    height: int
    fov_degrees: float = Field(description="horizontal field of view of the category's training camera")
    radius: float = Field(description="default camera distance from the scene centre")


class ModelInfo(BaseModel):
    bundle: BundleInfo
    field: dict = Field(description="the NeRF field config the hypernetwork emits")
    scene_box: list[list[float]] = Field(description="[[xmin, ymin, zmin], [xmax, ymax, zmax]], world units; +Z is up")
    camera: CameraInfo
    codes: CodeDims
    instances: int
    grid_resolution: int = Field(description="occupancy grid cells per axis built for every generated NeRF")
    text_to_nerf: bool
    retrieval: bool
    limits: Limits


class CacheStats(BaseModel):
    memory_hits: int
    disk_hits: int
    misses: int
    memory_evictions: int
    disk_evictions: int
    memory_bytes: int
    memory_entries: int
    memory_budget_bytes: int
    disk_bytes: int
    disk_entries: int
    disk_budget_bytes: int
