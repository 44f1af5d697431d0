"""An inversion submission checked and turned into a job request, and back into tensors in a worker.

Everything that can be wrong with a submission is found here, at submission, and answered 4xx
(problem+json): options beyond the caps, webhook targets outside the allow-list, files that are
not PNG/JPEG/WebP (415) or too large (413), masks that do not fit their image, poses that are not
rigid, not finite or inside the scene box, and views test-time optimisation cannot use
(``model.optimize.tto.check_inputs``). The stored request names its files by content address and
holds the resolved cameras and TTO settings, so a worker (on any machine) rebuilds exactly the
tensors that were checked.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass

import numpy as np
import torch
from pydantic import TypeAdapter, ValidationError

from model.denoise.finetune import DenoiseConfig, FinetuneConfig
from model.nerf.config import from_dict, to_dict
from model.nerf.rays import Intrinsics
from model.optimize.tto import TTOConfig, TTOError, check_inputs
from service.jobs.blobs import DiskBlobs, RedisBlobs
from service.jobs.webhooks import refusal
from service.poses import PoseError, check_pose, intrinsics, orbit_pose
from service.problems import ProblemError, field_errors
from service.resident import Resident
from service.schemas.jobs import InversionOptions, MatrixPose, OrbitPose, PoseSpec
from service.settings import Settings
from service.uploads import decode_image

POSES = TypeAdapter(list[PoseSpec])
KIND = "inversion"


@dataclass(frozen=True)
class Upload:
    """One uploaded file: the form's file name (for messages) and its bytes."""

    filename: str
    data: bytes


@dataclass
class Submission:
    """A checked inversion request, ready to become a job."""

    request: dict
    request_hash: str
    webhook_url: str | None


def _invalid(field: str, message: str, title: str = "Invalid inversion request") -> ProblemError:
    return ProblemError(422, title, f"{field}: {message}", kind="validation",
                        errors=[{"field": field, "loc": ["body", *field.split(".")], "message": message, "type": "value_error"}])


def _json_part(text: str | None, name: str):
    if text is None:
        return None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise _invalid(name, f"is not valid JSON ({exc.msg} at character {exc.pos})") from None


def parse_options(text: str | None, settings: Settings, resident: Resident) -> InversionOptions:
    """The ``options`` part, validated against the schema and the service's caps."""
    try:
        options = InversionOptions.model_validate(_json_part(text, "options") or {})
    except ValidationError as exc:
        errors = [{**e, "field": f"options.{e['field']}", "loc": ["body", "options", *e["loc"]]} for e in field_errors(exc.errors())]
        raise ProblemError(422, "Invalid inversion options", "; ".join(f"{e['field']}: {e['message']}" for e in errors[:5]),
                           kind="validation", errors=errors) from None
    unused = [name for name in ("denoise_steps", "denoise_rounds", "denoise_mirror") if getattr(options, name) is not None]
    if unused and not options.denoise:
        raise _invalid(f"options.{unused[0]}", f"{', '.join(unused)}: denoise-and-finetune settings, used only with "
                       "\"denoise\": true; add it or leave them out", "Denoise settings without denoise")
    cap = settings.limits.max_tto_steps
    total = (options.steps or TTOConfig.steps) + options.finetune_steps + (denoise_config(options).total_steps if options.denoise else 0)
    if total > cap:
        raise _invalid("options.steps", f"asks for {total} optimisation steps in all (steps + finetune_steps + denoise_steps x denoise_rounds); "
                       f"at most {cap} are allowed (HYPNERF_LIMITS__MAX_TTO_STEPS)", "Too many steps")
    if options.denoise and resident.bundle.denoiser_path is None:
        raise _invalid("options.denoise", "the served bundle has no denoiser; submit without denoise, or serve a bundle exported "
                       "with `hypnerf export --denoiser`")
    if options.webhook_url is not None:
        reason = refusal(options.webhook_url, settings)
        if reason:
            raise _invalid("options.webhook_url", reason, "Webhook refused")
    return options


def mask_to_alpha(mask_rgba: np.ndarray) -> np.ndarray:
    """A decoded mask ``[H, W, 4]`` -> alpha ``[H, W]``: its alpha channel when it has one, else its grey level."""
    alpha = mask_rgba[..., 3]
    return alpha if float(alpha.min()) < 1.0 else mask_rgba[..., :3].mean(-1)


def _decode_views(images: list[Upload], masks: list[Upload] | None, settings: Settings) -> np.ndarray:
    """RGBA ``[V, H, W, 4]`` in [0, 1] (a mask replaces the image's own alpha)."""
    limits = settings.limits
    decoded = [decode_image(u.data, max_pixels=limits.max_image_pixels, name=f"images[{i}] ({u.filename})") for i, u in enumerate(images)]
    height, width = decoded[0].shape[:2]
    for i, image in enumerate(decoded):
        if image.shape[:2] != (height, width):
            raise _invalid(f"images.{i}", f"is {image.shape[1]}x{image.shape[0]} but images.0 is {width}x{height}; "
                           "every image of one job must have the same size")
    if max(height, width) > limits.max_render_side:
        raise ProblemError(413, "Image too large", f"images are {width}x{height}; at most {limits.max_render_side} pixels a side "
                           "(HYPNERF_LIMITS__MAX_RENDER_SIDE); downscale them", kind="image-too-large")
    views = np.stack(decoded)
    if masks:
        if len(masks) != len(images):
            raise _invalid("masks", f"{len(masks)} masks for {len(images)} images; give one mask per image, or none")
        for i, upload in enumerate(masks):
            mask = decode_image(upload.data, max_pixels=limits.max_image_pixels, name=f"masks[{i}] ({upload.filename})")
            if mask.shape[:2] != (height, width):
                raise _invalid(f"masks.{i}", f"is {mask.shape[1]}x{mask.shape[0]} but its image is {width}x{height}")
            views[i, ..., 3] = mask_to_alpha(mask)
    return views


def _camera(spec, index: int, width: int, height: int, resident: Resident) -> tuple[np.ndarray, Intrinsics]:
    scene = resident.bundle.scene
    try:
        if isinstance(spec, OrbitPose):
            radius = spec.radius if spec.radius is not None else resident.default_radius
            pose = orbit_pose(scene, spec.azimuth, spec.elevation, radius)
            fov = spec.fov
        else:
            matrix = spec.c2w if isinstance(spec, MatrixPose) else spec
            if len(matrix) != 4 or any(len(row) != 4 for row in matrix):
                raise PoseError(f"a pose matrix must be 4x4 (four rows of four numbers), got rows of {[len(r) for r in matrix]}")
            pose = check_pose(np.asarray(matrix, dtype=np.float64), scene)
            fov = spec.fov if isinstance(spec, MatrixPose) else None
    except PoseError as exc:
        raise _invalid(f"poses.{index}", str(exc), "Invalid pose") from None
    return pose, intrinsics(width, height, fov if fov is not None else resident.default_fov)


def parse_poses(text: str | None, count: int, width: int, height: int, resident: Resident) -> tuple[np.ndarray | None, list[Intrinsics]]:
    """The ``poses`` part: one camera per image -> ``c2w [V, 4, 4]`` and intrinsics. Without it a
    single image's pose is searched for by the task (``c2w`` None, the training camera's field of view)."""
    if text is None:
        if count != 1:
            raise _invalid("poses", f"{count} images without poses; the pose search takes one image: send `poses`, one 4x4 "
                           "camera-to-world matrix or {azimuth, elevation, radius, fov} per image")
        return None, [intrinsics(width, height, resident.default_fov)]
    try:
        specs = POSES.validate_python(_json_part(text, "poses"))
    except ValidationError as exc:
        errors = [{**e, "field": f"poses.{e['field']}", "loc": ["body", "poses", *e["loc"]]} for e in field_errors(exc.errors())]
        raise ProblemError(422, "Invalid poses", "poses must be a list with one entry per image: a 4x4 matrix, {c2w, fov} or "
                           "{azimuth, elevation, radius, fov}", kind="validation", errors=errors[:20]) from None
    if len(specs) != count:
        raise _invalid("poses", f"{len(specs)} poses for {count} images; give one pose per image, in the order of the images")
    cameras = [_camera(spec, i, width, height, resident) for i, spec in enumerate(specs)]
    return np.stack([pose for pose, _ in cameras]), [camera for _, camera in cameras]


def tto_config(options: InversionOptions) -> TTOConfig:
    # progress (and should_stop) every step: a cancel is seen within one step
    values = {"finetune_steps": options.finetune_steps, "init": options.init, "seed": options.seed, "progress_every": 1}
    if options.steps is not None:
        values["steps"] = options.steps
    if options.rays_per_step is not None:
        values["rays_per_step"] = options.rays_per_step
    return from_dict(TTOConfig, values)


def denoise_config(options: InversionOptions) -> DenoiseConfig:
    steps = {"steps": options.denoise_steps} if options.denoise_steps is not None else {}
    rounds = {"rounds": options.denoise_rounds} if options.denoise_rounds is not None else {}
    mirror = {"mirror_inputs": options.denoise_mirror} if options.denoise_mirror is not None else {}
    return DenoiseConfig(finetune=FinetuneConfig(seed=options.seed, progress_every=1, **steps), **rounds, **mirror)


def request_digest(request: dict) -> str:
    """sha256 of the request's canonical JSON: equal submissions, equal digests."""
    return hashlib.sha256(json.dumps(request, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def prepare(images: list[Upload], masks: list[Upload] | None, poses: str | None, options: str | None,
            settings: Settings, resident: Resident, blobs: DiskBlobs | RedisBlobs) -> Submission:
    """Check a submission and store its files; returns the job request (raises ``ProblemError``)."""
    if not images:
        raise _invalid("images", "no image uploaded; send one or more `images` files (PNG, JPEG or WebP)")
    if len(images) > settings.limits.max_upload_images:
        raise _invalid("images", f"{len(images)} images; at most {settings.limits.max_upload_images} per job "
                       "(HYPNERF_LIMITS__MAX_UPLOAD_IMAGES)")
    opts = parse_options(options, settings, resident)
    views = _decode_views(images, masks, settings)
    c2w, cameras = parse_poses(poses, len(images), views.shape[2], views.shape[1], resident)
    try:
        check_inputs(torch.from_numpy(views), torch.from_numpy(c2w).float() if c2w is not None else None, cameras, resident.bundle.scene)
    except TTOError as exc:
        raise _invalid("images", str(exc), "Unusable views") from None
    request = {
        "images": [blobs.put(u.data) for u in images],
        "masks": [blobs.put(u.data) for u in masks] if masks else None,
        "c2w": c2w.tolist() if c2w is not None else None,
        "cameras": [to_dict(camera) for camera in cameras],
        "tto": to_dict(tto_config(opts)),
        "denoise": to_dict(denoise_config(opts)) if opts.denoise else None,
        "bundle": resident.bundle.digest,
    }
    digest = request_digest({**request, "webhook_url": opts.webhook_url})
    return Submission(request, digest, opts.webhook_url)


def load_views(request: dict, blobs: DiskBlobs | RedisBlobs) -> tuple[torch.Tensor, torch.Tensor | None, list[Intrinsics]]:
    """A stored request's views as ``images [V, H, W, 4]``, ``c2w [V, 4, 4]`` (None: to be searched) and intrinsics."""
    no_cap = math.inf  # checked at submission
    views = np.stack([decode_image(blobs.get(name), max_pixels=no_cap) for name in request["images"]])
    for i, name in enumerate(request["masks"] or ()):
        views[i, ..., 3] = mask_to_alpha(decode_image(blobs.get(name), max_pixels=no_cap))
    cameras = [from_dict(Intrinsics, camera) for camera in request["cameras"]]
    c2w = torch.tensor(request["c2w"], dtype=torch.float32) if request["c2w"] is not None else None
    return torch.from_numpy(views), c2w, cameras
