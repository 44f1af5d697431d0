"""Typed results and request parts of the hypnerf API (pydantic models).

They mirror the server's v1 schemas. Results accept fields this version does not know (a newer
server may add some) and keep them, so an older client keeps working; request parts
(``Codes``, ``Mix``, ``Interpolation``, ``InversionOptions``, ``OrbitPose``, ``MatrixPose``) forbid
unknown fields so a typo fails here, not on the server.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

JobStatus = Literal["queued", "running", "succeeded", "failed", "canceled"]
TERMINAL_STATUSES: tuple[str, ...] = ("succeeded", "failed", "canceled")


class Result(BaseModel):
    """Base of every result: unknown fields are kept (``model_extra``)."""

    model_config = ConfigDict(extra="allow")


class RequestPart(BaseModel):
    """Base of every request part: unknown fields are refused."""

    model_config = ConfigDict(extra="forbid")


# -- errors --------------------------------------------------------------------------------------


class FieldError(Result):
    """One invalid field of a 422: ``field`` is its dotted path (``codes.shape.0``, ``width``)."""

    field: str
    loc: list[str] = Field(default_factory=list)
    message: str
    type: str = ""


class Problem(Result):
    """An RFC 9457 problem details body (``application/problem+json``)."""

    type: str = "about:blank"
    title: str = ""
    status: int = 0
    detail: str | None = None
    instance: str | None = None
    errors: list[FieldError] | None = None


# -- health and model ----------------------------------------------------------------------------


class Health(Result):
    status: str


class Ready(Result):
    status: str
    bundle: str = Field(description="digest of the served bundle")
    load_seconds: float


class BundleInfo(Result):
    digest: str
    format: int
    created: str | None = None
    components: list[str] = Field(default_factory=list)


class CodeDims(Result):
    shape: int
    color: int


class CameraInfo(Result):
    width: int
    height: int
    fov_degrees: float
    radius: float


class Limits(Result):
    """The server's caps on what one request may ask for."""

    max_body_bytes: int
    max_image_pixels: int
    max_render_side: int
    max_turntable_side: int
    max_turntable_frames: int
    max_mesh_resolution: int
    max_texture_size: int
    max_pending_renders: int
    max_retrieve_k: int
    max_text_chars: int
    max_tto_steps: int
    max_queued_jobs: int
    max_upload_images: int


class ModelInfo(Result):
    bundle: BundleInfo
    field: dict[str, Any]
    scene_box: list[list[float]] = Field(description="[[xmin, ymin, zmin], [xmax, ymax, zmax]], +Z up")
    camera: CameraInfo
    codes: CodeDims
    instances: int
    grid_resolution: int
    text_to_nerf: bool
    retrieval: bool
    limits: Limits


class CacheStats(Result):
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


# -- instances -----------------------------------------------------------------------------------


class Attribution(Result):
    name: str | None = None
    creator: str | None = None
    licence: str | None = None
    source: str | None = None


class Instance(Result):
    id: str
    index: int
    caption: str | None = None
    shape_id: str | None = None
    attribution: Attribution | None = None


class InstancePage(Result):
    items: list[Instance]
    total: int
    offset: int
    limit: int
    next: str | None = None


# -- NeRFs ---------------------------------------------------------------------------------------


class Codes(Result):
    """Shape and colour codes (lengths from ``ModelInfo.codes``)."""

    shape: list[float]
    color: list[float]


class Mix(RequestPart):
    """One instance's shape with another's colour."""

    shape: str
    color: str


class Interpolation(RequestPart):
    """Codes interpolated linearly between instances ``a`` (t=0) and ``b`` (t=1)."""

    a: str
    b: str
    t: float = Field(0.5, ge=0.0, le=1.0)


class GridInfo(Result):
    resolution: int
    occupied_fraction: float
    box: list[list[float]] | None = None


class NerfLinks(Result):
    self: str
    render: str
    turntable: str
    mesh: str


class Nerf(Result):
    id: str = Field(description="content address: sha256 of the bundle digest and the codes")
    cached: bool
    source: dict[str, Any]
    created_at: str
    bundle: str
    codes: Codes | None = None
    grid: GridInfo
    bytes: int
    links: NerfLinks


class ColourWord(Result):
    name: str = Field(description="the colour name found in the prompt")
    palette: str = Field(description="the palette colour it was read as")


class TextNerf(Result):
    nerf: Nerf
    render_url: str
    read_as: str = Field(description="the prompt as the query network read it")
    colour_word: ColourWord | None = None


class Match(Result):
    instance: Instance
    score: float = Field(description="code-space similarity exp(-d) in (0, 1]; higher is closer")


class Retrieval(Result):
    k: int
    matches: list[Match]


# -- inversion jobs ------------------------------------------------------------------------------


class InversionOptions(RequestPart):
    """Options of an inversion job; ``None`` leaves a setting to the server's default."""

    steps: int | None = Field(None, ge=1)
    finetune_steps: int | None = Field(None, ge=0)
    rays_per_step: int | None = Field(None, ge=64)
    init: Literal["nearest", "mean"] | None = None
    seed: int | None = Field(None, ge=0)
    denoise: bool | None = None
    denoise_steps: int | None = Field(None, ge=1)
    denoise_rounds: int | None = Field(None, ge=1)
    denoise_mirror: bool | None = None
    webhook_url: str | None = None


class OrbitPose(RequestPart):
    """Where a photo was taken, as an orbit around the scene centre (degrees; +Z up)."""

    azimuth: float
    elevation: float
    radius: float | None = None
    fov: float | None = None


class MatrixPose(RequestPart):
    """A row-major 4x4 camera-to-world matrix (OpenGL: the camera looks down its -Z, +Y up)."""

    c2w: list[list[float]]
    fov: float | None = None


class JobProgress(Result):
    step: int
    steps: int
    phase: str | None = None
    loss: float | None = None
    psnr: float | None = None
    eta_s: float | None = None


class JobError(Result):
    title: str
    detail: str


class JobResult(Result):
    nerf_id: str
    codes: Codes
    finetuned: bool
    psnr: float | None = None
    steps: int
    init: str
    wall_s: float


class WebhookStatus(Result):
    url: str
    delivered: bool | None = None
    attempts: int = 0
    status_code: int | None = None
    error: str | None = None
    delivered_at: str | None = None


class JobLinks(Result):
    self: str
    events: str
    cancel: str
    nerf: str | None = None


class Job(Result):
    id: str
    kind: str
    status: JobStatus
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    attempts: int
    max_attempts: int
    cancel_requested: bool
    worker: str | None = None
    progress: JobProgress | None = None
    error: JobError | None = None
    result: JobResult | None = None
    webhook: WebhookStatus | None = None
    links: JobLinks

    @property
    def done(self) -> bool:
        """Whether the job reached a final status (succeeded, failed or canceled)."""
        return self.status in TERMINAL_STATUSES


class JobList(Result):
    items: list[Job]
    next: str | None = Field(None, description="cursor of the next page, None on the last")


class JobEvent(Result):
    """One server-sent event of ``jobs.events()``: the job as it is now."""

    id: str | None = None
    event: str
    job: Job
