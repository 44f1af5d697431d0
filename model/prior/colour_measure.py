"""The colour a generated NeRF shows: the palette name covering most of its rendered foreground.

A pixel is named by the palette colour (``model.data.colours``) nearest it in CIELAB (scikit-image's
``rgb2lab``) after that colour is scaled by the irradiance of the dataset renderer's shading range
that best matches the pixel, so a red seat in shadow stays red instead of turning brown. The
text-to-NeRF evaluation scores prompts with it (``model.eval.query``), and the query pipeline uses
it once per prior to tell which instances a colour dominates: a caption names a chair's largest
material, and the colour code of a plaid chair captioned purple paints a stool mostly grey.

Instances' rendered colours take a minute or two for a category prior on a CPU, so
:func:`rendered_colours` keeps them in ``$HYPNERF_CACHE/rendered-colours`` (default
``~/.cache/hypnerf``) under a digest of the prior's weights and the measure's settings, written
to a temporary name and renamed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from model.data.cameras import evaluation_poses
from model.data.colours import PALETTE, largest_share
from model.data.raycast import AMBIENT, LIGHTS, linear_to_srgb, srgb_to_linear
from model.nerf.cache import cache_folder
from model.nerf.rays import Intrinsics
from model.nerf.renderer import RenderConfig, render_image
from model.prior.codes import generated_grid

log = logging.getLogger(__name__)

COLOUR_POSES = (4, 5, 7)
"""Three of the fixed evaluation poses (40 degrees up, three sides) a NeRF's colour is read at."""
# the range of irradiance the ground-truth renderer's shading multiplies albedo by (ambient alone
# up to ambient plus every light head-on); generated NeRFs reproduce the same shading
IRRADIANCE = (AMBIENT, AMBIENT + sum(power for _, power in LIGHTS))
RENDERED_COLOUR_RESOLUTION = 64
"""Side of the renders an instance's colour is read from (the shares barely change with it)."""
MEASURE_VERSION = 1
"""Part of the cache key: bump when the naming or the renders change."""


def shading_invariant_names(rgb: np.ndarray) -> list[str]:
    """The palette name of each sRGB pixel ``[N, 3]`` up to shading: each palette colour is scaled
    in linear RGB by the irradiance (within :data:`IRRADIANCE`) that best matches the pixel, and
    the nearest scaled colour in CIELAB (Delta E, CIE76) names it."""
    from skimage.color import rgb2lab

    names = list(PALETTE)
    palette = srgb_to_linear(np.array([PALETTE[n] for n in names]))
    pixels = srgb_to_linear(np.clip(rgb, 0.0, 1.0))
    scale = np.clip(pixels @ palette.T / (palette**2).sum(1), *IRRADIANCE)  # [N, P]
    candidates = linear_to_srgb(scale[..., None] * palette[None])  # [N, P, 3]
    distance = np.linalg.norm(rgb2lab(candidates) - rgb2lab(np.clip(rgb, 0, 1))[:, None], axis=-1)
    return [names[i] for i in distance.argmin(axis=1)]


def dominant_colour_of(images: torch.Tensor, opacity: torch.Tensor, limit: int = 4000, seed: int = 0) -> tuple[str | None, dict[str, float]]:
    """The palette name (:func:`shading_invariant_names`) covering most foreground pixels of
    renders ``[V, H, W, 3]`` (opacity ``[V, H, W]`` > 0.5; at most ``limit`` drawn with a fixed
    seed) and each name's share."""
    pixels = images[opacity > 0.5].clamp(0, 1).cpu().numpy().astype(np.float64)
    if len(pixels) == 0:
        return None, {}
    if len(pixels) > limit:
        pixels = pixels[np.random.default_rng(seed).choice(len(pixels), limit, replace=False)]
    names = shading_invariant_names(pixels)
    shares = {name: names.count(name) / len(names) for name in set(names)}
    return largest_share(shares), shares


@torch.no_grad()
def render_codes(prior, shape: torch.Tensor, color: torch.Tensor, poses: np.ndarray, camera: Intrinsics) -> tuple[torch.Tensor, torch.Tensor]:
    """Renders ``[V, H, W, 3]`` and opacities ``[V, H, W]`` at ``poses [V, 4, 4]`` of the NeRF of
    codes ``[1, S]``, ``[1, C]`` (its occupancy grid from its own density)."""
    params = prior.net.params_from_codes(shape, color)
    grid = generated_grid(params, prior.net.cfg.field, prior.scene)
    outs = [render_image(params, prior.net.cfg.field, torch.as_tensor(p).float(), camera, RenderConfig(), scene=prior.scene, grid=grid) for p in poses]
    return torch.stack([o["rgb"] for o in outs]), torch.stack([o["opacity"] for o in outs])


def colour_camera(prior, resolution: int) -> Intrinsics:
    """The prior's camera resampled to ``resolution`` pixels a side (same field of view)."""
    cam = prior.meta["camera"]
    return Intrinsics.centred(width=resolution, height=resolution, focal=cam["fx"] * resolution / cam["width"])


def _weights_digest(prior) -> str:
    digest = hashlib.sha256()
    for name, tensor in sorted(prior.net.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:24]


def _cache_file(prior, resolution: int) -> Path:
    return cache_folder("rendered-colours") / f"{_weights_digest(prior)}-{resolution}-v{MEASURE_VERSION}.json"


def rendered_colours(prior, resolution: int = RENDERED_COLOUR_RESOLUTION, cache: bool = True) -> list[dict[str, float]]:
    """Each training instance's palette shares (:func:`dominant_colour_of`) in renders of its own
    codes at :data:`COLOUR_POSES`, ``resolution`` pixels a side, rounded to 3 digits; read from
    the cache when the same prior was measured before."""
    path = _cache_file(prior, resolution) if cache else None
    if path is not None and path.is_file():
        found = json.loads(path.read_text(encoding="utf-8"))
        if len(found) == len(prior.instances):
            return found
    camera, poses = colour_camera(prior, resolution), evaluation_poses()[list(COLOUR_POSES)]
    with torch.no_grad():
        shape_book, color_book = prior.net.codes(torch.arange(len(prior.instances), device=prior.device))
    shares = []
    for n in tqdm(range(len(prior.instances)), desc="instance colours", unit="instance", disable=len(prior.instances) < 16):
        images, opacity = render_codes(prior, shape_book[n : n + 1], color_book[n : n + 1], poses, camera)
        shares.append({name: round(share, 3) for name, share in sorted(dominant_colour_of(images, opacity)[1].items())})
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.tmp")
        partial.write_text(json.dumps(shares), encoding="utf-8")
        partial.replace(path)
        log.info("instance colours measured from renders; kept in %s", path)
    return shares
