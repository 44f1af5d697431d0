"""What a command hands the user for one NeRF: the NeRF itself, renders at the fixed evaluation
poses, a turntable and a mesh.

Layout of the output folder::

    nerf.safetensors    parameters (params.*) and occupancy grid (grid.*), safetensors (never pickle)
    nerf.json           scene box, field config and whatever the command adds (codes, provenance)
    renders/view_XX.png the 12 evaluation poses (model.data.cameras.evaluation_poses)
    turntable.gif       a loop at 30 degrees elevation (imageio: GIF needs no codec on the machine)
    mesh.glb            marching cubes of the rendered density, vertex colours (model.nerf.mesh)
"""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from safetensors.torch import load_file, save_file

from model.data.cameras import RADIUS, evaluation_poses, look_at, spherical_direction
from model.nerf import config
from model.nerf.fields import Field, FieldParams, field_config_from_dict
from model.nerf.images import save_png, to_uint8
from model.nerf.mesh import export_mesh, field_mesh
from model.nerf.occupancy import OccupancyGrid
from model.nerf.rays import Intrinsics
from model.nerf.renderer import RenderConfig, render_image
from model.nerf.scene import SceneBox


def turntable_poses(frames: int = 36, elevation: float = 30.0, radius: float = RADIUS) -> np.ndarray:
    """``[frames, 4, 4]`` look-at poses evenly spaced in azimuth at one elevation."""
    if frames < 1:
        raise ValueError("a turntable needs at least one frame")
    return np.stack([look_at(radius * spherical_direction(elevation, 360.0 * k / frames)) for k in range(frames)])


def render_poses(params: FieldParams, field_cfg: Field, grid: OccupancyGrid, scene: SceneBox, camera: Intrinsics,
                 poses: np.ndarray, cfg: RenderConfig | None = None) -> torch.Tensor:
    """Renders ``[N, H, W, 3]`` of one NeRF at camera-to-world ``poses [N, 4, 4]``."""
    cfg = cfg or RenderConfig()
    return torch.stack([
        render_image(params, field_cfg, torch.as_tensor(pose, dtype=torch.float32), camera, cfg, scene=scene, grid=grid)["rgb"].cpu()
        for pose in poses
    ])


def save_nerf(path: Path, params: FieldParams, grid: OccupancyGrid, scene: SceneBox, field_cfg: Field, extra: dict | None = None) -> None:
    """``path`` (``.safetensors``) and its ``.json`` sidecar."""
    tensors = {f"params.{k}": v.detach().contiguous().cpu() for k, v in params.items()}
    tensors.update({f"grid.{k}": v.contiguous().cpu() for k, v in grid.state_dict().items()})
    save_file(tensors, str(path))
    meta = {"scene_box": scene.to_aabb(), "field": config.to_dict(field_cfg), **(extra or {})}
    path.with_suffix(".json").write_text(json.dumps(meta, indent=2))


def load_nerf(path: Path) -> tuple[FieldParams, OccupancyGrid, SceneBox, Field, dict]:
    """What :func:`save_nerf` wrote."""
    path = Path(path)
    if not path.is_file() or not path.with_suffix(".json").is_file():
        raise FileNotFoundError(f"{path} and its .json sidecar are needed; write them with a command such as `hypnerf invert`")
    meta = json.loads(path.with_suffix(".json").read_text())
    tensors = load_file(str(path))
    params = {k.removeprefix("params."): v for k, v in tensors.items() if k.startswith("params.")}
    grid = OccupancyGrid.from_state_dict({k.removeprefix("grid."): v for k, v in tensors.items() if k.startswith("grid.")})
    return params, grid, SceneBox.from_aabb(meta.pop("scene_box")), field_config_from_dict(meta.pop("field")), meta


def write_outputs(out: Path, params: FieldParams, field_cfg: Field, grid: OccupancyGrid, scene: SceneBox, camera: Intrinsics, *,
                  extra: dict | None = None, turntable_frames: int = 36, mesh_resolution: int = 128) -> dict[str, str]:
    """Write the NeRF, its evaluation renders, turntable and mesh into ``out``; returns the paths written."""
    out = Path(out)
    (out / "renders").mkdir(parents=True, exist_ok=True)
    save_nerf(out / "nerf.safetensors", params, grid, scene, field_cfg, extra)
    for k, image in enumerate(render_poses(params, field_cfg, grid, scene, camera, evaluation_poses())):
        save_png(out / "renders" / f"view_{k:02d}.png", image)
    frames = render_poses(params, field_cfg, grid, scene, camera, turntable_poses(turntable_frames))
    iio.imwrite(out / "turntable.gif", np.stack([to_uint8(f) for f in frames]), duration=80, loop=0)
    export_mesh(field_mesh(params, field_cfg, grid, scene, mesh_resolution), out / "mesh.glb")
    return {"nerf": str(out / "nerf.safetensors"), "renders": str(out / "renders"), "turntable": str(out / "turntable.gif"), "mesh": str(out / "mesh.glb")}
