"""Inversion jobs: the options and poses of a submission, and a job as the API shows it."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from service.jobs.records import STATUSES, Job
from service.schemas.common import FiniteFloat
from service.schemas.nerfs import Codes, Orbit

JobStatus = Literal[STATUSES]


class InversionOptions(BaseModel):
    """The ``options`` part of an inversion submission (JSON)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"steps": 300, "seed": 0}]})

    steps: int | None = Field(None, ge=1, description="code-optimisation steps (at most limits.max_tto_steps); default 300")
    finetune_steps: int = Field(0, ge=0, description="steps optimising the NeRF's own parameters after the codes (counted in the same cap)")
    rays_per_step: int | None = Field(None, ge=64, le=65536, description="rays sampled from the images per step; default 2048")
    init: Literal["nearest", "mean"] = Field("nearest", description="start from the training instance that looks closest, or the mean code")
    seed: int = Field(0, ge=0, le=2**31 - 1)
    denoise: bool = Field(False, description="after the codes, render fixed views, denoise them and finetune on them and the input images (needs a bundle with a denoiser)")
    denoise_steps: int | None = Field(None, ge=1, description="finetune steps on the denoised views per round; default 300 (all rounds counted in the same cap)")
    denoise_rounds: int | None = Field(None, ge=1, le=4, description="times render, denoise and finetune run, each on the NeRF the round before finetuned; default 2")
    denoise_mirror: bool | None = Field(None, description="finetune on the input images' mirror images too (a left-right symmetric object; false for one that is not); default true")
    webhook_url: str | None = Field(None, max_length=2048, description="POSTed the job (HMAC-signed) when it finishes; its host must be in HYPNERF_WEBHOOK_ALLOW")


class MatrixPose(BaseModel):
    """An explicit camera-to-world matrix (OpenGL convention: the camera looks down its -Z, +Y up)."""

    model_config = ConfigDict(extra="forbid")

    c2w: list[list[float]] = Field(description="row-major 4x4; rotation orthonormal, bottom row 0,0,0,1, camera outside the scene box")
    fov: float | None = Field(None, gt=1.0, lt=170.0, allow_inf_nan=False, description="horizontal field of view in degrees; default the training camera's")


class OrbitPose(Orbit):
    """A look-at camera on a sphere around the scene centre (the render endpoint's orbit); azimuth
    and elevation are required here, since they describe where a photo was taken."""

    model_config = ConfigDict(extra="forbid")

    azimuth: FiniteFloat = Field(description="degrees from +X towards +Y around +Z")
    elevation: float = Field(ge=-89.0, le=89.0, allow_inf_nan=False, description="degrees above the XY plane")


PoseSpec = list[list[float]] | MatrixPose | OrbitPose
"""One image's pose: a bare 4x4 matrix, ``{"c2w", "fov"}`` or ``{"azimuth", "elevation", "radius", "fov"}``."""


class JobProgress(BaseModel):
    step: int = Field(description="steps done (codes, then finetune)")
    steps: int = Field(description="steps planned; the run may end earlier when the loss stops improving")
    phase: str | None = Field(None, description="`codes`, `finetune` or `denoise`")
    loss: float | None = None
    psnr: float | None = Field(None, description="PSNR of the sampled rays at this step (dB)")
    eta_s: float | None = Field(None, description="seconds left if the remaining steps run as fast as the ones done")


class JobError(BaseModel):
    title: str
    detail: str


class JobResult(BaseModel):
    nerf_id: str = Field(description="the inverted NeRF, in the NeRF cache: GET /v1/nerfs/{nerf_id}/render")
    codes: Codes = Field(description="the optimised shape and colour codes (POST /v1/nerfs with them recreates the NeRF unless it was finetuned)")
    finetuned: bool = Field(description="whether the NeRF's own parameters were optimised after the codes")
    psnr: float | None = Field(None, description="PSNR of the last step's sampled rays (dB)")
    steps: int = Field(description="optimisation steps run")
    init: str = Field(description="where the codes started: `nearest:<instance number>`, `mean` or `given`")
    wall_s: float


class WebhookStatus(BaseModel):
    url: str
    delivered: bool | None = Field(None, description="null until a delivery was tried")
    attempts: int = 0
    status_code: int | None = Field(None, description="HTTP status of the last attempt")
    error: str | None = Field(None, description="why the last attempt failed")
    delivered_at: str | None = None


class JobLinks(BaseModel):
    self: str
    events: str
    cancel: str
    nerf: str | None = None


class JobView(BaseModel):
    """A job as ``GET /v1/jobs/{id}`` answers it (and as webhooks send it)."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "id": "8c7d2f0e4b1a4c3e9f6a5b4c3d2e1f00", "kind": "inversion", "status": "running", "created_at": "2025-01-01T12:00:00Z",
        "started_at": "2025-01-01T12:00:01Z", "finished_at": None, "attempts": 1, "max_attempts": 3, "cancel_requested": False,
        "progress": {"step": 120, "steps": 300, "phase": "codes", "loss": 0.012, "psnr": 21.4, "eta_s": 9.5},
        "error": None, "result": None, "webhook": None,
        "links": {"self": "/v1/jobs/8c7d2f0e4b1a4c3e9f6a5b4c3d2e1f00", "events": "/v1/jobs/8c7d2f0e4b1a4c3e9f6a5b4c3d2e1f00/events",
                  "cancel": "/v1/jobs/8c7d2f0e4b1a4c3e9f6a5b4c3d2e1f00/cancel", "nerf": None},
    }]})

    id: str
    kind: str
    status: JobStatus
    created_at: str
    started_at: str | None = Field(None, description="when the current (last) attempt started")
    finished_at: str | None = None
    attempts: int = Field(description="starts so far; a job whose worker was lost is started again, up to max_attempts")
    max_attempts: int
    cancel_requested: bool
    worker: str | None = Field(None, description="the worker holding the job while it runs (host:pid:tag)")
    progress: JobProgress | None = None
    error: JobError | None = None
    result: JobResult | None = None
    webhook: WebhookStatus | None = None
    links: JobLinks

    @classmethod
    def of(cls, job: Job) -> JobView:
        base = f"/v1/jobs/{job.id}"
        return cls(
            id=job.id, kind=job.kind, status=job.status, created_at=iso_time(job.created_at), started_at=iso_time(job.started_at),
            finished_at=iso_time(job.finished_at), attempts=job.attempts, max_attempts=job.max_attempts,
            cancel_requested=job.cancel_requested, worker=job.lease_owner,
            progress=JobProgress(**job.progress) if job.progress else None,
            error=JobError(**job.error) if job.error else None,
            result=JobResult(**job.result) if job.result else None,
            webhook=WebhookStatus(**job.webhook) if job.webhook else None,
            links=JobLinks(self=base, events=f"{base}/events", cancel=f"{base}/cancel",
                           nerf=f"/v1/nerfs/{job.result['nerf_id']}" if job.result else None),
        )


class JobList(BaseModel):
    items: list[JobView]
    next: str | None = Field(None, description="cursor of the next page (pass as `cursor`), null on the last page")


def iso_time(timestamp: float | None) -> str | None:
    """Unix seconds as ISO 8601 UTC with milliseconds (``2025-01-01T12:00:00.123Z``)."""
    if timestamp is None:
        return None
    return datetime.fromtimestamp(timestamp, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
