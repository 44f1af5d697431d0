"""Inversion jobs: submit (multipart), read, list, cancel, follow progress (server-sent events).

Handlers that touch the jobs store or decode images are plain functions, which FastAPI runs in
its thread pool: nothing here blocks the event loop, and the optimisation itself runs in worker
processes (``service.jobs``).
"""

from __future__ import annotations

import base64
import binascii
import json
from typing import Annotated

import anyio
from fastapi import APIRouter, File, Form, Header, Query, Request, Response, UploadFile
from fastapi.responses import StreamingResponse

from service.jobs import JobSystem
from service.jobs.events import job_events
from service.jobs.inputs import Upload, prepare
from service.jobs.records import CANCELED, TERMINAL, IdempotencyConflict, QueueFull
from service.problems import ProblemError
from service.routers.deps import ResidentDep
from service.schemas.common import PROBLEM_RESPONSES
from service.schemas.jobs import JobList, JobStatus, JobView

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], responses={code: PROBLEM_RESPONSES[code] for code in (404, 422, 503)})

POSES_HELP = ("JSON list, one entry per image, in order: a row-major 4x4 camera-to-world matrix (OpenGL convention: the camera "
              "looks down its -Z, +Y up), `{\"c2w\": [[...]], \"fov\": 40}` or `{\"azimuth\": 30, \"elevation\": 20, \"radius\": 2, "
              "\"fov\": 40}` (degrees; radius and fov default to the training camera's). Leave it out for a single image "
              "of unknown pose: the pose is searched on a grid of look-at cameras, then refined with the codes")
OPTIONS_HELP = "JSON object: steps, finetune_steps, rays_per_step, init, seed, denoise, denoise_steps, denoise_rounds, denoise_mirror, webhook_url (all optional)"


def get_jobs(request: Request) -> JobSystem:
    jobs = getattr(request.app.state, "jobs", None)
    if jobs is None:
        raise ProblemError(503, "Jobs unavailable", "the job system is not running on this server", kind="not-ready")
    return jobs


def _job_or_404(jobs: JobSystem, job_id: str):
    job = jobs.get(job_id)
    if job is None:
        raise ProblemError(404, "Unknown job", f"no job {job_id}; list jobs with GET /v1/jobs", kind="unknown-job")
    return job


def _uploads(files: list[UploadFile] | None) -> list[Upload]:
    return [Upload(f.filename or f"file {i}", f.file.read()) for i, f in enumerate(files or ())]


@router.post("/inversions", status_code=202, response_model=JobView, summary="submit an inversion job (images + poses)",
             responses={code: PROBLEM_RESPONSES[code] for code in (413, 415, 429)} | {
                 409: {"description": "the idempotency key was used for a different request"}})
def create_inversion(
    request: Request,
    response: Response,
    resident: ResidentDep,
    images: Annotated[list[UploadFile], File(description="one or more PNG, JPEG or WebP files (RGB, or RGBA with the object's mask as alpha)")],
    masks: Annotated[list[UploadFile] | None, File(description="optional: one mask per image (alpha, or grey levels), same size as its image")] = None,
    poses: Annotated[str | None, Form(description=POSES_HELP)] = None,
    options: Annotated[str | None, Form(description=OPTIONS_HELP)] = None,
    idempotency_key: Annotated[str | None, Header(max_length=255, description="retrying with the same key and body returns the same job")] = None,
) -> JobView:
    """Queue test-time optimisation of the prior's codes to the uploaded views. Answers 202 with the
    job and `Location: /v1/jobs/{id}`; poll it, follow `/events`, or receive the webhook."""
    jobs = get_jobs(request)
    submission = prepare(_uploads(images), _uploads(masks), poses, options, jobs.settings, resident, jobs.blobs)
    try:
        job, created = jobs.submit(submission, idempotency_key)
    except IdempotencyConflict:
        raise ProblemError(409, "Idempotency key reused", "this Idempotency-Key was used for a different request; use a new key "
                           "for a new job", kind="idempotency-conflict") from None
    except QueueFull as full:
        raise ProblemError(429, "Job queue full", f"{full.active} inversion jobs are queued or running, the most this server takes "
                           "(HYPNERF_LIMITS__MAX_QUEUED_JOBS); retry after the Retry-After seconds", kind="queue-full",
                           headers={"Retry-After": str(jobs.retry_after())}) from None
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    if not created:
        response.headers["Idempotent-Replayed"] = "true"
    return JobView.of(job)


@router.get("/{job_id}", response_model=JobView, summary="a job: status, progress, error or result")
def read_job(request: Request, job_id: str) -> JobView:
    return JobView.of(_job_or_404(get_jobs(request), job_id))


@router.post("/{job_id}/cancel", response_model=JobView, summary="cancel a job",
             responses={409: {"description": "the job already finished"}})
def cancel_job(request: Request, job_id: str) -> JobView:
    """A queued job is canceled at once; a running one stops within a step (its status turns
    `canceled` then). Canceling a canceled job is a no-op."""
    jobs = get_jobs(request)
    job = _job_or_404(jobs, job_id)
    if job.status in TERMINAL and job.status != CANCELED:
        raise ProblemError(409, "Job already finished", f"job {job_id} already {job.status}; nothing to cancel", kind="job-finished")
    job = jobs.cancel(job_id)
    return JobView.of(job)


def _cursor(text: str | None) -> tuple[float, str] | None:
    if text is None:
        return None
    try:
        created_at, job_id = json.loads(base64.urlsafe_b64decode(text.encode()))
        return float(created_at), str(job_id)
    except (ValueError, TypeError, binascii.Error):
        raise ProblemError(422, "Invalid cursor", "cursor must be the `next` value of a previous page", kind="validation",
                           errors=[{"field": "cursor", "loc": ["query", "cursor"], "message": "not a cursor from this API",
                                    "type": "value_error"}]) from None


@router.get("", response_model=JobList, summary="list jobs, newest first")
def list_jobs(
    request: Request,
    status: Annotated[JobStatus | None, Query(description="only jobs with this status")] = None,
    limit: Annotated[int, Query(ge=1, le=100)] = 20,
    cursor: Annotated[str | None, Query(max_length=200, description="the `next` of the previous page")] = None,
) -> JobList:
    found = get_jobs(request).list(status=status, limit=limit + 1, before=_cursor(cursor))
    page = found[:limit]
    following = None
    if len(found) > limit:
        last = page[-1]
        following = base64.urlsafe_b64encode(json.dumps([last.created_at, last.id]).encode()).decode()
    return JobList(items=[JobView.of(job) for job in page], next=following)


@router.get("/{job_id}/events", summary="server-sent events of a job's progress until it finishes",
            response_class=StreamingResponse, responses={200: {"content": {"text/event-stream": {}},
                                                               "description": "`event: job` with the job JSON each time it changes"}})
def job_event_stream(request: Request, job_id: str) -> StreamingResponse:
    jobs = get_jobs(request)
    _job_or_404(jobs, job_id)

    async def read() -> JobView | None:
        job = await anyio.to_thread.run_sync(jobs.get, job_id)
        return JobView.of(job) if job is not None else None

    return StreamingResponse(job_events(read, request.is_disconnected), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
