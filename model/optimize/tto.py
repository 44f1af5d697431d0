"""Test-time optimisation (TTO): a NeRF for an object the prior has never seen, from one or more
posed images.

The hypernetwork stays frozen; the shape and colour codes are optimised through the shared
photometric step (``model.optimize.step``) on random rays of the input views. The start is the
caller's guess (the query network's), else the codebook entry whose render at the input poses is
closest (a cheap first loss over every instance), else the mean code. A Mahalanobis penalty keeps
the codes near the codebook's distribution (a Gaussian with a shrunk covariance): codes far from
it decode to haze. The generated NeRF's occupancy grid is maintained from its own density during
the optimisation, starting from the grid of the starting codes, so empty space costs nothing.
After the codes, an optional finetune of the NeRF's own parameters (hash tables and weights),
pulled towards the prior's output, recovers detail the codes cannot express. Early stopping
ends a run whose loss stops improving.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from dataclasses import field as dataclass_field

import torch

from model.data.dataset import validate_views
from model.nerf.fields import Field, FieldParams, world_density
from model.nerf.occupancy import MaintainedGrid, OccupancyConfig, OccupancyGrid
from model.nerf.rays import Intrinsics
from model.nerf.renderer import RenderConfig, render_rays
from model.nerf.scene import SceneBox
from model.optimize.pose import PixelBank, PoseRefinement, candidate_poses
from model.optimize.step import RayBatch, adam_with_decay, mse_to_psnr, photometric_loss
from model.prior.codes import generated_grid
from model.prior.hypernet import HyperNetwork

log = logging.getLogger(__name__)


@dataclass
class TTOConfig:
    """Settings of a test-time optimisation (serialisable with ``model.nerf.config``)."""

    steps: int = 300
    rays_per_step: int = 2048
    lr: float = 3e-2
    final_lr_factor: float = 0.1
    code_prior_weight: float = 1e-4
    """Weight of the mean Mahalanobis distance of the codes to the codebook's Gaussian."""
    init: str = "nearest"
    """Start when no guess is given: ``nearest`` (the instance whose render at the inputs is closest) or ``mean``."""
    init_rays: int = 512
    init_samples_per_ray: int = 32
    """The first loss of every instance is cheap: few rays, coarse samples."""
    init_shapes: int = 4
    """The nearest-instance start scores one instance per shape first (by silhouette when the
    inputs have alpha), then every colour variant of this many best shapes; 0 scores every instance."""
    finetune_steps: int = 0
    finetune_lr: float = 1e-3
    finetune_pull: float = 1.0
    """Weight of the squared distance of the finetuned parameters to the prior's output (per element, mean)."""
    mirror: bool = False
    """Add each view mirrored across the scene box's x = centre plane, a virtual second view of a
    left-right symmetric object (the datasets' furniture faces -Y, so its symmetry plane is x = 0)."""
    refine_pose: bool = False
    """Optimise each view's pose with the codes (always on when the pose is unknown)."""
    pose_lr: float = 3e-3
    search_azimuths: int = 12
    search_elevations: tuple[float, ...] = (10.0, 30.0, 50.0, 70.0)
    search_radii: tuple[float, ...] = (2.0,)
    search_codes: int = 8
    """Codebook entries (spread over the shapes) each candidate pose of an unknown-pose search is scored with."""
    patience: int = 60
    """Stop when the smoothed loss has not improved by ``min_improvement`` for this many steps (0: never)."""
    min_improvement: float = 1e-3
    render: RenderConfig = dataclass_field(default_factory=lambda: RenderConfig(termination_threshold=0.0))
    occupancy: OccupancyConfig = dataclass_field(default_factory=lambda: OccupancyConfig(update_every=16, warmup_steps=16))
    progress_every: int = 10
    seed: int = 0

    def __post_init__(self):
        if self.steps < 1 or self.rays_per_step < 1 or self.init_rays < 1:
            raise ValueError("steps, rays_per_step and init_rays must be at least 1")
        if self.finetune_steps < 0 or self.patience < 0 or self.init_shapes < 0:
            raise ValueError("finetune_steps, patience and init_shapes must not be negative")
        if not (self.lr > 0 and self.finetune_lr > 0) or not all(math.isfinite(v) for v in (self.lr, self.finetune_lr, self.code_prior_weight, self.finetune_pull)):
            raise ValueError("learning rates must be positive and every weight finite")
        if self.init not in ("nearest", "mean"):
            raise ValueError(f"init must be 'nearest' or 'mean', not {self.init!r}")


@dataclass
class TTOResult:
    shape_code: torch.Tensor
    """``[S]``"""
    color_code: torch.Tensor
    """``[C]``"""
    params: FieldParams
    """The final NeRF (from the codes, or finetuned), batch 1, detached, on the CPU."""
    grid: OccupancyGrid
    history: list[dict]
    """``{"step", "phase", "loss", "psnr", "elapsed_s"}`` every ``progress_every`` steps."""
    stopped: bool
    """Whether ``should_stop`` ended the run early."""
    init: str
    """Where the codes started: ``given``, ``nearest:<instance>`` or ``mean``."""
    c2w: torch.Tensor
    """``[V, 4, 4]`` the input views' poses used at the end (refined, or found by the search; not
    the mirrored virtual views')."""
    wall_s: float


class TTOError(ValueError):
    """Inputs TTO cannot work with; the message says what to change."""


# ---------------------------------------------------------------------------------------------
# The codebook's distribution


@dataclass
class CodeGaussian:
    """A Gaussian fitted on codebook rows: mean ``[D]`` and the inverse of the shrunk covariance ``[D, D]``."""

    mean: torch.Tensor
    precision: torch.Tensor

    @classmethod
    def fit(cls, codes: torch.Tensor, shrinkage: float = 0.1) -> "CodeGaussian":
        """Fit on rows ``[N, D]``; the covariance is shrunk towards its mean variance, so it is
        invertible even with fewer rows than dimensions (51 shapes, 128 dimensions)."""
        codes = codes.detach().float()
        mean = codes.mean(0)
        centred = codes - mean
        cov = centred.T @ centred / max(codes.shape[0] - 1, 1)
        scale = cov.diagonal().mean().clamp_min(1e-12)
        shrunk = (1 - shrinkage) * cov + shrinkage * scale * torch.eye(codes.shape[1], device=codes.device)
        return cls(mean, torch.linalg.inv(shrunk))

    def distance2(self, code: torch.Tensor) -> torch.Tensor:
        """Squared Mahalanobis distance per dimension of ``code [..., D]``: zero at the mean, growing
        fastest along directions in which the codebook does not vary."""
        d = code - self.mean
        return (d @ self.precision * d).sum(-1) / d.shape[-1]


def codebook(net: HyperNetwork) -> tuple[torch.Tensor, torch.Tensor]:
    """Every instance's (shape ``[I, S]``, colour ``[I, C]``) codes."""
    return net.codes(torch.arange(net.instances, device=next(net.parameters()).device))


# ---------------------------------------------------------------------------------------------
# Inputs


def check_inputs(images: torch.Tensor, c2w: torch.Tensor | None, cameras: Sequence[Intrinsics], scene: SceneBox) -> None:
    """Refuse inputs TTO cannot use, saying why: shapes, non-finite values, intrinsics that do not
    match the images, cameras inside the scene box, images with no object in them. ``c2w`` None
    (unknown poses) skips the pose checks."""
    try:
        validate_views(images, c2w if c2w is not None else torch.eye(4).expand(images.shape[0], 4, 4))
    except ValueError as err:
        raise TTOError(str(err)) from None
    if images.shape[-1] != 4:
        raise TTOError("images must be RGBA [V, H, W, 4] (alpha all 1 for a photo without a mask)")
    if len(cameras) != images.shape[0]:
        raise TTOError(f"{images.shape[0]} images but {len(cameras)} cameras; give one camera per image")
    for i, camera in enumerate(cameras):
        if (camera.height, camera.width) != tuple(images.shape[1:3]):
            raise TTOError(f"image {i} is {images.shape[2]}x{images.shape[1]} but its camera is {camera.width}x{camera.height}")
    if c2w is not None:
        check_poses(c2w, scene)
    alpha = images[..., 3]
    empty = (alpha.flatten(1).amax(1) < 0.5).nonzero().flatten().tolist()
    if empty:
        raise TTOError(f"images {empty} have no object (their masks are empty); give a view with the object in it")
    rgb_white = (images[..., :3].flatten(1, 2).amin(1) > 0.999).all(-1) & (alpha.flatten(1).amin(1) > 0.999)
    blank = rgb_white.nonzero().flatten().tolist()
    if blank:
        raise TTOError(f"images {blank} are blank white; give a photo of the object (or RGBA with its mask)")


def check_poses(c2w: torch.Tensor, scene: SceneBox) -> None:
    """Camera-to-world matrices ``[V, 4, 4]`` need an orthonormal rotation and a camera outside the scene box."""
    rotation = c2w[:, :3, :3].float()
    eye = torch.eye(3).expand_as(rotation)
    if (rotation.transpose(1, 2) @ rotation - eye).abs().max() > 1e-3:
        raise TTOError("a pose's rotation is not orthonormal; give camera-to-world matrices with a rotation part")
    lo, hi = scene.tensors("cpu")
    centres = c2w[:, :3, 3].float()
    inside = ((centres > lo) & (centres < hi)).all(-1).nonzero().flatten().tolist()
    if inside:
        raise TTOError(f"cameras {inside} are inside the scene box; TTO needs views from outside the object")


# ---------------------------------------------------------------------------------------------
# Losses


def _render_loss(params: FieldParams, field_cfg: Field, batch: RayBatch, cfg: RenderConfig, scene: SceneBox,
                 grid: OccupancyGrid | None, has_alpha: bool, generator: torch.Generator):
    return photometric_loss(params, field_cfg, batch, cfg, scene=scene, grid=grid, random_background=has_alpha, generator=generator)


@torch.no_grad()
def instance_losses(net: HyperNetwork, field_cfg: Field, scene: SceneBox, batch: RayBatch, cfg: RenderConfig,
                    instances: Sequence[int] | None = None, silhouette: bool = False) -> torch.Tensor:
    """Loss ``[I]`` of each of ``instances`` (default: all) on ``batch``, rendered without jitter:
    the squared error of the render over white to the image over white, or with ``silhouette``
    of the render's opacity to the image's alpha (what the shape alone decides)."""
    device = batch.origins.device
    alpha = batch.rgba[:, 3:]
    white = torch.ones(3, device=device)
    target = batch.rgba[:, :3] * alpha + white * (1 - alpha)
    shapes, colors = codebook(net)
    losses = []
    for n in range(len(shapes)) if instances is None else instances:
        params = net.params_from_codes(shapes[n : n + 1], colors[n : n + 1])
        out = render_rays(params, field_cfg, batch.origins, batch.directions, cfg, scene=scene, background=white)
        losses.append(torch.mean((out["opacity"].reshape(-1, 1) - alpha) ** 2) if silhouette else torch.mean((out["rgb"] - target) ** 2))
    return torch.stack(losses)


def nearest_instance(net: HyperNetwork, field_cfg: Field, scene: SceneBox, batch: RayBatch, cfg: RenderConfig,
                     shortlist: int, silhouette: bool) -> int:
    """The codebook instance whose render is closest to ``batch``. With ``shortlist`` > 0, in two
    rounds: the first instance of every shape scored (by ``silhouette`` when the image has alpha,
    so a shape is not ruled out by the colour of the variant that stands for it), then every
    instance of the ``shortlist`` best shapes by colour; a fraction of the hypernetwork
    evaluations of scoring all instances when the codebook holds several colours per shape."""
    shape_of = net.shape_index.tolist()
    if not shortlist or shortlist >= max(shape_of) + 1:
        return int(torch.argmin(instance_losses(net, field_cfg, scene, batch, cfg)))
    first: dict[int, int] = {}
    for n, s in enumerate(shape_of):
        first.setdefault(s, n)
    scores = instance_losses(net, field_cfg, scene, batch, cfg, list(first.values()), silhouette)
    kept = {list(first)[int(i)] for i in torch.argsort(scores)[:shortlist]}
    candidates = [n for n, s in enumerate(shape_of) if s in kept]
    return candidates[int(torch.argmin(instance_losses(net, field_cfg, scene, batch, cfg, candidates)))]


def with_mirrored_views(images: torch.Tensor, c2w: torch.Tensor, cameras: Sequence[Intrinsics], scene: SceneBox):
    """The views plus each one mirrored across the plane x = the scene box's centre: the image
    flipped left-right, seen by the mirrored camera (a reflection of its pose, its x axis flipped
    to stay right-handed, and its principal point mirrored)."""
    lo, hi = scene.tensors(c2w.device)
    centre = float((lo[0] + hi[0]) / 2)
    flip = torch.diag(torch.tensor([-1.0, 1.0, 1.0], device=c2w.device))
    mirrored = c2w.clone()
    mirrored[:, :3, :3] = flip @ c2w[:, :3, :3] @ flip
    mirrored[:, 0, 3] = 2 * centre - c2w[:, 0, 3]
    flipped = [Intrinsics(c.width, c.height, c.fx, c.fy, c.width - c.cx, c.cy) for c in cameras]
    return torch.cat([images, images.flip(2)]), torch.cat([c2w, mirrored]), [*cameras, *flipped]


@torch.no_grad()
def search_pose(net: HyperNetwork, scene: SceneBox, pixels: PixelBank, cfg: TTOConfig, render: RenderConfig,
                generator: torch.Generator) -> torch.Tensor:
    """The candidate look-at pose ``[1, 4, 4]`` (``model.optimize.pose.candidate_poses``) whose
    render, by the best of ``cfg.search_codes`` codebook entries spread over the shapes, is closest
    to the image on the same few rays."""
    device = pixels.rgba.device
    candidates = candidate_poses(cfg.search_azimuths, cfg.search_elevations, cfg.search_radii).to(device)
    shapes, colors = codebook(net)
    picks = torch.linspace(0, net.instances - 1, min(cfg.search_codes, net.instances)).round().long().tolist()
    nerfs = [net.params_from_codes(shapes[i : i + 1], colors[i : i + 1]) for i in picks]
    white = torch.ones(3, device=device)
    pixel_pick = torch.randint(pixels.rgba.shape[1], (cfg.init_rays,), generator=generator, device=device)
    target_rgba = pixels.rgba[0, pixel_pick]
    target = target_rgba[:, :3] * target_rgba[:, 3:] + (1 - target_rgba[:, 3:])
    best, best_loss = 0, math.inf
    for number, pose in enumerate(candidates):
        directions = (pose[:3, :3] @ pixels.directions[0, pixel_pick][..., None]).squeeze(-1)
        directions = directions / directions.norm(dim=-1, keepdim=True)
        origins = pose[:3, 3].expand_as(directions)
        for params in nerfs:
            out = render_rays(params, net.cfg.field, origins, directions, render, scene=scene, background=white)
            loss = float(torch.mean((out["rgb"] - target) ** 2))
            if loss < best_loss:
                best, best_loss = number, loss
    log.info("pose search: candidate %d of %d (loss %.4f)", best, len(candidates), best_loss)
    return candidates[best : best + 1]


# ---------------------------------------------------------------------------------------------
# The optimisation


def invert(
    net: HyperNetwork,
    scene: SceneBox,
    images: torch.Tensor,
    c2w: torch.Tensor | None,
    cameras: Sequence[Intrinsics],
    cfg: TTOConfig,
    *,
    init: tuple[torch.Tensor, torch.Tensor] | None = None,
    progress: Callable[[dict], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    snapshot: Callable[[dict, torch.Tensor, torch.Tensor], None] | None = None,
) -> TTOResult:
    """Optimise codes (then optionally the NeRF itself) to reproduce ``images [V, H, W, 4]``
    (straight-alpha RGBA in [0, 1]) seen from ``c2w [V, 4, 4]`` through ``cameras``.

    ``c2w`` None means the pose is unknown: a single image's pose is searched for
    (:func:`search_pose`) and refined with the codes.
    ``progress`` receives ``{"step", "steps", "phase", "loss", "psnr", "elapsed_s"}`` every
    ``cfg.progress_every`` steps; ``should_stop`` is polled as often and ends the run early
    (the result so far is returned with ``stopped``). ``snapshot`` receives the same entry with
    the current shape and colour codes (for speed-against-error curves).
    """
    images = torch.as_tensor(images).float()
    c2w = torch.as_tensor(c2w).float() if c2w is not None else None
    check_inputs(images, c2w, cameras, scene)
    device = next(net.parameters()).device
    field_cfg = net.cfg.field
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    input_views = images.shape[0]
    if cfg.mirror and c2w is not None:
        images, c2w, cameras = with_mirrored_views(images, c2w, cameras, scene)
    pixels = PixelBank(images, cameras, device)
    has_alpha = bool((images[..., 3] < 1).any())
    start = time.perf_counter()
    total_steps = cfg.steps + cfg.finetune_steps

    for p in net.parameters():
        p.requires_grad_(False)
    shapes, colors = codebook(net)
    shape_prior, color_prior = CodeGaussian.fit(net.shape_codes.weight), CodeGaussian.fit(colors)
    coarse = replace(cfg.render, samples_per_ray=cfg.init_samples_per_ray)
    searched = c2w is None
    if searched:
        if len(images) != 1:
            raise TTOError("a pose search takes one image; give the poses of several views")
        c2w = search_pose(net, scene, pixels, cfg, coarse, generator)
    c2w = c2w.to(device)
    if init is not None:
        shape0, color0 = (torch.as_tensor(c, dtype=torch.float32, device=device).reshape(-1) for c in init)
        if shape0.numel() != shapes.shape[1] or color0.numel() != colors.shape[1]:
            raise TTOError(f"the starting codes must have {shapes.shape[1]} + {colors.shape[1]} values")
        started = "given"
    elif cfg.init == "nearest":
        best = nearest_instance(net, field_cfg, scene, pixels.sample(cfg.init_rays, c2w, generator), coarse, cfg.init_shapes, has_alpha)
        shape0, color0 = shapes[best], colors[best]
        started = f"nearest:{best}"
    else:
        shape0, color0 = net.shape_codes.weight.mean(0), colors.mean(0)
        started = "mean"
    shape = shape0.detach().clone().requires_grad_(True)
    color = color0.detach().clone().requires_grad_(True)
    pose = PoseRefinement(c2w)
    refine = cfg.refine_pose or searched

    with torch.no_grad():
        first = net.params_from_codes(shape[None], color[None])
    occupancy = MaintainedGrid(scene, cfg.occupancy, start=generated_grid(first, field_cfg, scene, cfg.occupancy.resolution, seed=cfg.seed),
                               device=device)
    history: list[dict] = []
    stopped = False

    def report(step: int, phase: str, loss: float, mse: float) -> bool:
        """Record progress; returns whether the caller asked to stop."""
        entry = {"step": step, "steps": total_steps, "phase": phase, "loss": loss, "psnr": mse_to_psnr(mse),
                 "elapsed_s": time.perf_counter() - start}
        history.append(entry)
        if progress is not None:
            progress(entry)
        return should_stop is not None and should_stop()

    # Phase 1: the codes (and the poses)
    groups = [{"params": [shape, color], "lr": cfg.lr}]
    if refine:
        groups.append({"params": list(pose.parameters()), "lr": cfg.pose_lr})
    optimizer, scheduler = adam_with_decay(groups, lr=cfg.lr, steps=cfg.steps, final_lr_factor=cfg.final_lr_factor)
    plateau = _Plateau(cfg.patience, cfg.min_improvement)
    for step in range(cfg.steps):
        params = net.params_from_codes(shape[None], color[None])
        occupancy.step(step, world_density({k: v.detach() for k, v in params.items()}, field_cfg, scene))
        poses = pose() if refine else c2w
        batch = pixels.sample(cfg.rays_per_step, poses, generator)
        mse, _ = _render_loss(params, field_cfg, batch, cfg.render, scene, occupancy.grid, has_alpha, generator)
        penalty = shape_prior.distance2(shape) + color_prior.distance2(color)
        loss = mse + cfg.code_prior_weight * penalty
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        if not torch.isfinite(loss):
            raise TTOError("the optimisation diverged (non-finite loss); try a smaller lr")
        if step % cfg.progress_every == 0 or step == cfg.steps - 1:
            stop = report(step, "codes", loss.item(), mse.item())
            if snapshot is not None:
                snapshot(history[-1], shape.detach().clone(), color.detach().clone())
            if stop:
                stopped = True
                break
        if plateau.done(mse.item()):
            log.info("codes converged after %d steps", step + 1)
            break

    with torch.no_grad():
        params = {k: v.detach() for k, v in net.params_from_codes(shape[None], color[None]).items()}
        final_poses = (pose() if refine else c2w).detach()
    grid = occupancy.update(world_density(params, field_cfg, scene))

    # Phase 2: the NeRF's own parameters, pulled towards the prior's output
    if cfg.finetune_steps and not stopped:
        params, grid, stopped = _finetune(params, field_cfg, scene, pixels, final_poses, cfg, occupancy, has_alpha, generator,
                                          lambda s, l, m: report(cfg.steps + s, "finetune", l, m))
    return TTOResult(
        shape_code=shape.detach().cpu(), color_code=color.detach().cpu(), params={k: v.detach().cpu() for k, v in params.items()},
        grid=grid.to("cpu"), history=history, stopped=stopped, init=started, c2w=final_poses[:input_views].cpu(), wall_s=time.perf_counter() - start,
    )


def _finetune(prior_params: FieldParams, field_cfg: Field, scene: SceneBox, pixels: PixelBank, c2w: torch.Tensor, cfg: TTOConfig,
              occupancy: MaintainedGrid, has_alpha: bool, generator: torch.Generator, report: Callable[[int, float, float], bool]):
    params = {k: v.clone().requires_grad_(True) for k, v in prior_params.items()}
    optimizer, scheduler = adam_with_decay(list(params.values()), lr=cfg.finetune_lr, steps=cfg.finetune_steps, final_lr_factor=cfg.final_lr_factor)
    count = sum(v.numel() for v in params.values())
    stopped = False
    for step in range(cfg.finetune_steps):
        occupancy.step(step, world_density({k: v.detach() for k, v in params.items()}, field_cfg, scene))
        mse, _ = _render_loss(params, field_cfg, pixels.sample(cfg.rays_per_step, c2w, generator), cfg.render, scene, occupancy.grid, has_alpha, generator)
        pull = sum(((params[k] - prior_params[k]) ** 2).sum() for k in params) / count
        loss = mse + cfg.finetune_pull * pull
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        if (step % cfg.progress_every == 0 or step == cfg.finetune_steps - 1) and report(step, loss.item(), mse.item()):
            stopped = True
            break
    final = {k: v.detach() for k, v in params.items()}
    return final, occupancy.update(world_density(final, field_cfg, scene)), stopped


class _Plateau:
    """Early stopping on an exponentially smoothed loss."""

    def __init__(self, patience: int, min_improvement: float, smoothing: float = 0.9):
        self.patience, self.min_improvement, self.smoothing = patience, min_improvement, smoothing
        self.smoothed = None
        self.best = math.inf
        self.since = 0

    def done(self, value: float) -> bool:
        if self.patience == 0:
            return False
        self.smoothed = value if self.smoothed is None else self.smoothing * self.smoothed + (1 - self.smoothing) * value
        if self.smoothed < self.best * (1 - self.min_improvement):
            self.best, self.since = self.smoothed, 0
        else:
            self.since += 1
        return self.since >= self.patience
