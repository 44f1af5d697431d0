"""ONNX Runtime against torch on one bundle: the emitted NeRF parameters and a render of each, and
the query network's codes.

The bundle's ONNX graphs and their torch networks read the same stored weights, so they must
agree to float32 rounding; this is what ``hypnerf export --verify`` reports and the tests bound.
Both parameter sets are rendered with the same occupancy grid (built from the torch NeRF's own
density), so the image difference measures the parameters alone.
"""

from __future__ import annotations

import numpy as np
import torch

from model.bundle.load import Bundle
from model.data.cameras import look_at, spherical_direction
from model.nerf.renderer import RenderConfig, render_image
from model.prior.codes import generated_grid
from model.prior.query import load_query


def parity_pose(bundle: Bundle, elevation_deg: float = 30.0, azimuth_deg: float = 45.0) -> torch.Tensor:
    """A camera-to-world pose ``[4, 4]`` looking at the scene box's centre from twice its longest side."""
    centre = (np.array(bundle.scene.min) + np.array(bundle.scene.max)) / 2
    eye = centre + 2.0 * bundle.scene.longest_side * spherical_direction(elevation_deg, azimuth_deg)
    return torch.from_numpy(look_at(eye, centre)).float()


@torch.no_grad()
def parity(bundle: Bundle, shape: np.ndarray, color: np.ndarray, render: RenderConfig | None = None) -> dict:
    """``{"params_max_abs_diff", "image_max_abs_diff", "coverage"}`` between ONNX Runtime and torch for
    codes ``[S]``, ``[C]``; ``coverage`` is the fraction of pixels the object covers (opacity > 0.5)."""
    from_onnx = bundle.generate(shape, color)
    net = bundle.hypernet()
    from_torch = net.params_from_codes(torch.from_numpy(np.asarray(shape, np.float32))[None], torch.from_numpy(np.asarray(color, np.float32))[None])
    params_diff = max(float((from_onnx[name] - from_torch[name]).abs().max()) for name in from_torch)
    grid = generated_grid(from_torch, bundle.field, bundle.scene)
    pose, cfg = parity_pose(bundle), render or RenderConfig()
    renders = [render_image(p, bundle.field, pose, bundle.camera, cfg, scene=bundle.scene, grid=grid) for p in (from_onnx, from_torch)]
    return {
        "params_max_abs_diff": params_diff,
        "image_max_abs_diff": float((renders[0]["rgb"] - renders[1]["rgb"]).abs().max()),
        "coverage": float((renders[1]["opacity"] > 0.5).float().mean()),
    }


@torch.no_grad()
def query_parity(bundle: Bundle) -> float:
    """Max abs difference of the query network's raw codes, ONNX Runtime vs torch, on the retrieval
    bank's embeddings placed in the image slot (the inputs it was trained on)."""
    if bundle.query is None:
        raise ValueError(f"{bundle.path} has no query network")
    query, net = bundle.query, load_query(bundle.path)
    slot = query.slot("image")
    joint = np.zeros((len(query.bank), query.input_dim), np.float32)
    joint[:, slot.offset : slot.offset + slot.dim] = query.bank
    shape, color = net(torch.from_numpy(joint))
    worst = 0.0
    for row in range(len(joint)):
        onnx_shape, onnx_color = query.codes(joint[row], snap=False)
        worst = max(worst, float(np.abs(onnx_shape - shape[row].numpy()).max()), float(np.abs(onnx_color - color[row].numpy()).max()))
    return worst
