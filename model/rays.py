"""Camera rays and ray/box intersection.

Cameras follow the NeRF-synthetic (OpenGL) convention used by ``transforms.json``: a 4x4
camera-to-world matrix, the camera looks down its -Z axis with +Y up and +X right.
Pixel centres sit at half-integer offsets.
"""

from __future__ import annotations

import math

import torch

# Smallest magnitude a direction component may take before its reciprocal is clamped: keeps
# slab intersection finite for grazing and axis-parallel rays (1/0 would give inf*0 = NaN).
_MIN_DIRECTION = 1e-9


def focal_from_fov(width: int, camera_angle_x: float) -> float:
    """Focal length in pixels from the horizontal field of view in radians."""
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


def camera_directions(width: int, height: int, focal: float, *, device=None, dtype=torch.float32) -> torch.Tensor:
    """Unnormalised ray directions in the camera frame, ``[H, W, 3]``."""
    j, i = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype) + 0.5,
        torch.arange(width, device=device, dtype=dtype) + 0.5,
        indexing="ij",
    )
    return torch.stack([(i - 0.5 * width) / focal, -(j - 0.5 * height) / focal, -torch.ones_like(i)], dim=-1)


def pixel_rays(c2w: torch.Tensor, width: int, height: int, focal: float) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays through every pixel centre.

    ``c2w`` is ``[..., 4, 4]``; returns origins and unit directions, each ``[..., H, W, 3]``.
    """
    cam = camera_directions(width, height, focal, device=c2w.device, dtype=c2w.dtype)
    rot = c2w[..., None, None, :3, :3]
    directions = (rot @ cam[..., None]).squeeze(-1)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    origins = c2w[..., None, None, :3, 3].expand_as(directions)
    return origins, directions


def ray_box_intersection(
    origins: torch.Tensor, directions: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor, min_near: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slab test of rays ``[..., 3]`` against an axis-aligned box.

    Returns ``near``, ``far`` (``[...]``) and ``hit`` (``far > near``). ``near`` is clamped to
    ``min_near`` so a camera inside the box starts marching at its own position.
    """
    small = directions.abs() < _MIN_DIRECTION
    safe = torch.where(small, torch.where(directions < 0, -_MIN_DIRECTION, _MIN_DIRECTION), directions)
    inv = 1.0 / safe
    t0 = (box_min - origins) * inv
    t1 = (box_max - origins) * inv
    near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(min_near)
    far = torch.maximum(t0, t1).amin(dim=-1)
    hit = far > near
    return near, far, hit
