"""Denoise and finetune (paper section 3.1, step 2): render a NeRF at m fixed poses, denoise the
renders image by image, and finetune the NeRF's own parameters (hash tables and MLP weights, not
the codes that produced them) on the denoised views.

The finetune uses the shared photometric step (``model.optimize.step``) on random rays of the
denoised views, over a random background per ray since the denoised views have alpha, with Adam
and an exponential decay. Its occupancy grid is maintained from the field's own density
(``model.nerf.occupancy.MaintainedGrid``), limited to the starting NeRF's grid grown by a few
cells: the finetune refines the object the NeRF already holds and cannot grow floaters far from
it. An L2 pull towards the starting parameters keeps the NeRF near what the prior produced, so
the views that were not denoised stay consistent with the ones that were (the paper's claim that
finetuning, not fitting from scratch, keeps the NeRF multi-view consistent).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path

import torch

from model.data.cameras import RADIUS, poses_from_directions, spherical_direction
from model.data.dataset import Views, validate_views
from model.denoise.io import load_denoiser
from model.denoise.vqvae import VQVAE2Denoiser, denoise_renders
from model.nerf import config
from model.nerf.fields import Field, FieldParams, world_density
from model.nerf.occupancy import MaintainedGrid, OccupancyConfig, OccupancyGrid, dilate
from model.nerf.rays import Intrinsics
from model.nerf.renderer import RenderConfig, render_image
from model.nerf.scene import SceneBox
from model.optimize.fit import training_rays
from model.optimize.step import RayBatch, adam_with_decay, mse_to_psnr, photometric_loss
from model.optimize.tto import with_mirrored_views
from model.prior.codes import generated_grid
from model.prior.io import Prior


@dataclass
class FinetuneConfig:
    """How the NeRF's own parameters are finetuned on (denoised) views."""

    render: RenderConfig = dataclass_field(default_factory=lambda: RenderConfig(termination_threshold=0.0))
    occupancy: OccupancyConfig = dataclass_field(default_factory=lambda: OccupancyConfig(warmup_steps=16))
    steps: int = 300
    rays_per_step: int = 2048
    lr: float = 3e-3
    final_lr_factor: float = 0.1
    anchor_weight: float = 1.0  # weight of the mean squared distance to the starting parameters
    grid_dilation: int = 2  # cells the starting grid may grow by
    progress_every: int = 25
    seed: int = 0


@dataclass
class DenoiseConfig:
    """Denoise and finetune: the renders that get denoised, then the finetune."""

    render: RenderConfig = dataclass_field(default_factory=RenderConfig)
    finetune: FinetuneConfig = dataclass_field(default_factory=FinetuneConfig)
    input_share: float = 0.5
    """Share of the finetune views that are copies of the input views, when they are given: the
    photos are evidence, the denoised views a guess (chosen on a development set of deformed copies
    of the training meshes, ``benchmarks.bench_denoiser_selection``: of 0, 0.2 and 0.5, 0.5 best; with
    two rounds on 12 such objects 0.67 and 0.8 lose 0.09 and 0.21 dB foreground to it)."""
    rounds: int = 2
    """Times the whole step runs, each round rendering and denoising the NeRF the round before
    finetuned: a cleaner NeRF renders views the denoiser cleans further (chosen on the same
    development set, ``benchmarks.bench_denoise_rounds``: +0.68, +0.93 and +0.99 dB foreground over
    TTO after 1, 2 and 3 rounds; a third adds little for another round's time)."""

    mirror_inputs: bool = True
    """Add each input view mirrored across the plane x = the scene box's centre (the image flipped,
    seen by the mirrored camera) as a virtual view, sharing the inputs' copies: a chair is
    left-right symmetric, so its photo also shows the other side (chosen on the same development
    set, two rounds: +0.20 dB foreground, 11 of 12 objects better; turn it off for an object that
    is not symmetric)."""

    def __post_init__(self):
        if not 0.0 <= self.input_share < 1.0:
            raise ValueError(f"input_share is a share of the finetune views in [0, 1), got {self.input_share}")
        if self.rounds < 1:
            raise ValueError(f"denoise-and-finetune needs at least one round, got {self.rounds}")

    @property
    def total_steps(self) -> int:
        """Finetune steps over all rounds."""
        return self.rounds * self.finetune.steps


@dataclass
class DenoiseResult:
    """The finetuned NeRF (``params`` batch 1, detached, with its ``grid``), what it was finetuned
    on (``renders [m, H, W, 3]`` over white, ``denoised [m, H, W, 4]`` straight alpha) and the
    seconds each stage took (``render_s``, ``denoise_s``, ``finetune_s``, ``total_s``)."""

    params: FieldParams
    grid: OccupancyGrid
    renders: torch.Tensor
    denoised: torch.Tensor
    timings: dict[str, float]


def ring_poses(elevations: Sequence[float] = (20.0, 50.0), per_ring: int = 8, radius: float = RADIUS) -> torch.Tensor:
    """The fixed poses to denoise: rings on the upper hemisphere at ``elevations`` (degrees) of
    ``per_ring`` azimuths each (rings turned half a step against each other), looking at the
    origin from ``radius``; ``[len(elevations) * per_ring, 4, 4]``."""
    if per_ring < 1 or not elevations or not all(0 < e < 90 for e in elevations):
        raise ValueError("ring poses need at least one pose per ring and elevations strictly between 0 and 90 degrees")
    step = 360.0 / per_ring
    directions = [spherical_direction(e, (k + 0.5 * (r % 2)) * step) for r, e in enumerate(elevations) for k in range(per_ring)]
    return torch.from_numpy(poses_from_directions(directions, radius)).float()


def anchor_loss(params: FieldParams, start: FieldParams) -> torch.Tensor:
    """Sum over the NeRF's tensors of the mean squared distance to the starting values."""
    return sum(torch.mean((params[k] - start[k]) ** 2) for k in params)


def finetune_on_views(
    params: FieldParams,
    field: Field,
    scene: SceneBox,
    images: torch.Tensor,
    c2w: torch.Tensor,
    cameras: Sequence[Intrinsics],
    cfg: FinetuneConfig,
    *,
    grid: OccupancyGrid | None = None,
    progress: Callable[[dict], None] | None = None,
) -> FieldParams:
    """Finetune a NeRF's own parameters on posed views; returns the new parameters (batch 1, detached).

    ``images [V, H, W, 4]`` straight-alpha RGBA in [0, 1] (trained over a random background when
    some alpha is below 1, else against their own pixels over ``cfg.render.background``), ``c2w
    [V, 4, 4]``, one camera per view. ``grid`` is the starting NeRF's occupancy grid (computed from
    its density when ``None``). ``progress`` is called every ``cfg.progress_every`` steps with
    ``{"step", "steps", "loss", "psnr", "anchor", "elapsed_s"}``.
    """
    device = next(iter(params.values())).device
    rays = training_rays(posed_views(images, c2w, cameras, scene, device), device)
    return finetune_on_rays(params, field, scene, rays, cfg, grid=grid, progress=progress)


def posed_views(images: torch.Tensor, c2w: torch.Tensor, cameras: Sequence[Intrinsics], scene: SceneBox, device) -> Views:
    """Checked finetune views on ``device``: RGBA ``images [V, H, W, 4]``, poses ``[V, 4, 4]``, one camera each."""
    validate_views(images, c2w)
    if images.shape[-1] != 4 or c2w.shape[1:] != (4, 4):
        raise ValueError("finetune views must be RGBA [V, H, W, 4] (alpha all 1 when there is no mask) with [V, 4, 4] poses")
    if len(cameras) != images.shape[0]:
        raise ValueError(f"need one camera per view, got {len(cameras)} for {images.shape[0]} views")
    return Views(images.float().to(device), c2w.float().to(device), list(cameras), scene, [f"view_{i}" for i in range(len(cameras))], None)


def finetune_on_rays(
    params: FieldParams,
    field: Field,
    scene: SceneBox,
    rays: RayBatch,
    cfg: FinetuneConfig,
    *,
    grid: OccupancyGrid | None = None,
    progress: Callable[[dict], None] | None = None,
) -> FieldParams:
    """:func:`finetune_on_views` on a pool of rays ``[P, 3]`` with RGBA targets ``[P, 4]`` (the
    pixels of views of any sizes), drawn uniformly each step."""
    if cfg.steps < 0 or cfg.rays_per_step < 1:
        raise ValueError("finetune steps must be >= 0 and rays_per_step >= 1")
    device = next(iter(params.values())).device
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    start_grid = grid.to(device) if grid is not None else generated_grid(params, field, scene, cfg.occupancy.resolution, seed=cfg.seed)
    if start_grid.resolution != cfg.occupancy.resolution:
        raise ValueError(f"the starting grid has resolution {start_grid.resolution}, the finetune's occupancy config {cfg.occupancy.resolution}")
    limit = OccupancyGrid(dilate(start_grid.occupied, cfg.grid_dilation), start_grid.box_min, start_grid.box_max)
    maintained = MaintainedGrid(scene, cfg.occupancy, limit=limit, device=device)

    start = {k: v.detach().clone() for k, v in params.items()}
    params = {k: v.detach().clone().requires_grad_() for k, v in params.items()}
    optimizer, scheduler = adam_with_decay(list(params.values()), lr=cfg.lr, steps=cfg.steps, final_lr_factor=cfg.final_lr_factor)
    random_background = bool((rays.rgba[:, 3] < 1.0).any())  # some pixel has a mask
    began = time.perf_counter()
    for step in range(cfg.steps):
        maintained.step(step, world_density(params, field, scene))
        idx = torch.randint(0, len(rays), (cfg.rays_per_step,), device=device, generator=generator)
        batch = RayBatch(rays.origins[idx], rays.directions[idx], rays.rgba[idx])
        mse, _ = photometric_loss(
            params, field, batch, cfg.render, scene=scene, grid=maintained.grid, random_background=random_background, generator=generator
        )
        anchor = anchor_loss(params, start)
        optimizer.zero_grad(set_to_none=True)
        (mse + cfg.anchor_weight * anchor).backward()
        optimizer.step()
        scheduler.step()
        if progress is not None and (step % cfg.progress_every == 0 or step == cfg.steps - 1):
            progress({"step": step, "steps": cfg.steps, "loss": mse.item(), "psnr": mse_to_psnr(mse.item()), "anchor": anchor.item(),
                      "elapsed_s": time.perf_counter() - began})
    return {k: v.detach() for k, v in params.items()}


def denoise_and_finetune(
    params: FieldParams,
    field: Field,
    scene: SceneBox,
    denoiser: VQVAE2Denoiser,
    poses: torch.Tensor,
    camera: Intrinsics,
    cfg: DenoiseConfig,
    *,
    grid: OccupancyGrid | None = None,
    inputs: tuple[torch.Tensor, torch.Tensor, Sequence[Intrinsics]] | None = None,
    progress: Callable[[dict], None] | None = None,
) -> DenoiseResult:
    """Render ``params`` (batch 1) at ``poses [m, 4, 4]`` with ``camera``, denoise the renders and
    finetune the NeRF on them (``finetune_on_rays``), ``cfg.rounds`` times, each round starting
    from the one before; the result's grid comes from the finetuned density, its renders and
    denoised views are the last round's. ``grid`` is the NeRF's occupancy grid (e.g.
    ``TTOResult.grid``; computed when ``None``). ``inputs`` (the RGBA images ``[n, H, W, 4]``, poses
    ``[n, 4, 4]`` and cameras the NeRF was inverted from; any size, not only ``camera``'s) join the
    finetune views' rays, repeated to make up ``cfg.input_share`` of them (with their mirror images
    when ``cfg.mirror_inputs``). ``progress`` counts steps over all rounds.
    """
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] < 1:
        raise ValueError(f"poses must be [m, 4, 4] camera-to-world matrices with m >= 1, got {tuple(poses.shape)}")
    device = next(iter(params.values())).device
    resolution = cfg.finetune.occupancy.resolution
    grid = grid.to(device) if grid is not None else generated_grid(params, field, scene, resolution, seed=cfg.finetune.seed)
    poses = poses.float().to(device)
    input_rays = None
    if inputs is not None:
        input_images, input_c2w, input_cameras = inputs
        if input_c2w.shape[0] != len(input_images) or len(input_cameras) != len(input_images):
            raise ValueError(f"{len(input_images)} input images need as many poses and cameras, got {input_c2w.shape[0]} and {len(input_cameras)}")
        if cfg.mirror_inputs:
            input_images, input_c2w, input_cameras = with_mirrored_views(input_images, input_c2w.to(device), input_cameras, scene)
        input_rays = training_rays(posed_views(input_images, input_c2w, input_cameras, scene, device), device)
    timings = dict.fromkeys(("render_s", "denoise_s", "finetune_s", "total_s"), 0.0)
    for round_index in range(cfg.rounds):
        began = time.perf_counter()
        outs = [render_image(params, field, pose, camera, cfg.render, scene=scene, grid=grid) for pose in poses]
        rgb, opacity = torch.stack([o["rgb"] for o in outs]), torch.stack([o["opacity"] for o in outs])
        rendered = time.perf_counter()
        denoised = denoise_renders(denoiser, rgb, opacity)
        cleaned = time.perf_counter()
        rays = with_inputs(training_rays(posed_views(denoised, poses, [camera] * len(poses), scene, device), device), input_rays, cfg.input_share)
        params = finetune_on_rays(params, field, scene, rays, cfg.finetune, grid=grid,
                                  progress=_offset_progress(progress, round_index * cfg.finetune.steps, cfg.total_steps))
        grid = generated_grid(params, field, scene, resolution, seed=cfg.finetune.seed)
        done = time.perf_counter()
        for key, seconds in (("render_s", rendered - began), ("denoise_s", cleaned - rendered), ("finetune_s", done - cleaned), ("total_s", done - began)):
            timings[key] += seconds
    return DenoiseResult(params, grid, rgb, denoised, timings)


def _offset_progress(progress: Callable[[dict], None] | None, offset: int, total: int) -> Callable[[dict], None] | None:
    """``progress`` seeing a round's steps as steps ``offset + step`` of ``total``."""
    if progress is None:
        return None
    return lambda report: progress({**report, "step": offset + report["step"], "steps": total})


def with_inputs(rays: RayBatch, input_rays: RayBatch | None, share: float) -> RayBatch:
    """The denoised views' rays ``[P, 3]`` (targets ``[P, 4]``) plus the input views' rays, repeated so
    that they make up ``share`` of the pool (at least one copy): input photos of any size weigh by
    their share, not their pixel count."""
    if input_rays is None or share == 0.0:
        return rays
    copies = max(1, round(share / (1.0 - share) * len(rays) / len(input_rays)))
    return RayBatch(*(torch.cat([a, b.repeat(copies, 1)]) for a, b in
                      ((rays.origins, input_rays.origins), (rays.directions, input_rays.directions), (rays.rgba, input_rays.rgba))))


def denoise_and_finetune_prior(folder: Path, cfg: DenoiseConfig | None = None, poses: torch.Tensor | None = None,
                               ) -> Callable[..., tuple[FieldParams, OccupancyGrid]]:
    """``(prior, params, inputs=None, progress=None) -> (params, grid)``: denoise-and-finetune of a
    NeRF of ``prior`` (e.g. a TTO result's) with the denoiser in ``folder``, at ``poses`` (default
    ``ring_poses()``) seen through the prior's category camera; the denoiser is loaded once.
    ``inputs`` and ``progress`` are :func:`denoise_and_finetune`'s."""
    denoiser, _ = load_denoiser(folder)
    cfg = cfg or DenoiseConfig()
    poses = ring_poses() if poses is None else poses

    def run(prior: Prior, params: FieldParams, inputs=None, progress: Callable[[dict], None] | None = None) -> tuple[FieldParams, OccupancyGrid]:
        camera = config.from_dict(Intrinsics, prior.meta["camera"])
        result = denoise_and_finetune(params, prior.net.cfg.field, prior.scene, denoiser.to(prior.device), poses, camera, cfg,
                                      inputs=inputs, progress=progress)
        return result.params, result.grid

    return run
