"""Cameras and rays: pinhole intrinsics, pixel rays and ray/box intersection.

Cameras follow the NeRF-synthetic (OpenGL) convention used by ``transforms.json``: a 4x4
camera-to-world matrix, the camera looks down its -Z axis with +Y up and +X right. Intrinsics are
a pinhole with focal lengths ``fx``, ``fy`` and principal point ``cx``, ``cy`` in pixels (image
rows grow downwards); pixel centres sit at half-integer offsets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

# Smallest magnitude a direction component may take before its reciprocal is clamped: keeps
# slab intersection finite for grazing and axis-parallel rays (1/0 would give inf*0 = NaN).
_MIN_DIRECTION = 1e-9


def focal_from_fov(width: int, camera_angle_x: float) -> float:
    """Focal length in pixels from the horizontal field of view in radians."""
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera: image size in pixels, focal lengths and principal point in pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        if not (isinstance(self.width, int) and isinstance(self.height, int)) or self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive integers, got {self.width}x{self.height}")
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be finite and positive and the principal point finite, got fx={self.fx}, fy={self.fy}, cx={self.cx}, cy={self.cy}")

    @classmethod
    def centred(cls, width: int, height: int, focal: float) -> Intrinsics:
        """Square pixels and the principal point at the image centre."""
        return cls(int(width), int(height), float(focal), float(focal), 0.5 * width, 0.5 * height)

    @classmethod
    def from_fov(cls, width: int, height: int, camera_angle_x: float) -> Intrinsics:
        return cls.centred(width, height, focal_from_fov(width, camera_angle_x))

    @property
    def pixels(self) -> int:
        return self.width * self.height


def camera_directions(camera: Intrinsics, *, device=None, dtype=torch.float32) -> torch.Tensor:
    """Unnormalised ray directions in the camera frame, ``[H, W, 3]`` (z = -1)."""
    j, i = torch.meshgrid(
        torch.arange(camera.height, device=device, dtype=dtype) + 0.5,
        torch.arange(camera.width, device=device, dtype=dtype) + 0.5,
        indexing="ij",
    )
    return torch.stack([(i - camera.cx) / camera.fx, -(j - camera.cy) / camera.fy, -torch.ones_like(i)], dim=-1)


def project(points_cam: torch.Tensor, camera: Intrinsics) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Camera-frame points ``[N, 3]`` -> pixel coordinates ``x [N]``, ``y [N]`` and depth ``[N]``
    (positive in front of the camera); the inverse of :func:`camera_directions`."""
    depth = -points_cam[:, 2]
    safe = depth.clamp_min(1e-6)
    x = points_cam[:, 0] / safe * camera.fx + camera.cx
    y = -points_cam[:, 1] / safe * camera.fy + camera.cy
    return x, y, depth


def pixel_rays(c2w: torch.Tensor, camera: Intrinsics) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays through every pixel centre.

    ``c2w`` is ``[..., 4, 4]``; returns origins and unit directions, each ``[..., H, W, 3]``.
    """
    cam = camera_directions(camera, device=c2w.device, dtype=c2w.dtype)
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
