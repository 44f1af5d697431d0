"""Camera poses during test-time optimisation: joint refinement of a roughly known pose, and a
coarse search when the pose is unknown.

Refinement: each view's camera-to-world matrix is ``[R0 exp(w) | t0 + dt]``, with an axis-angle
update ``w`` in the camera's own frame and a translation update ``dt``, both starting at zero and
optimised with the codes (rays are rebuilt from the refined pose every step). Search: the object
is assumed to sit at the scene centre, seen by a look-at camera; candidate poses on a grid of
azimuths, elevations and distances are scored by how well a NeRF of the prior (the best of a few
codebook entries) explains the image at a few hundred rays, and the best candidate is refined.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from model.data.cameras import look_at, spherical_direction
from model.nerf.rays import Intrinsics, camera_directions
from model.optimize.step import RayBatch


def axis_angle_to_matrix(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[..., 3, 3]`` of axis-angle vectors ``w [..., 3]`` (Rodrigues), smooth
    at zero: the series of sin(t)/t and (1 - cos t)/t^2 is used for tiny angles."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp_min(1e-12).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-12))
    zero = torch.zeros_like(w[..., 0])
    k = torch.stack([
        torch.stack([zero, -w[..., 2], w[..., 1]], -1),
        torch.stack([w[..., 2], zero, -w[..., 0]], -1),
        torch.stack([-w[..., 1], w[..., 0], zero], -1),
    ], -2)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    return eye + a * k + b * (k @ k)


def rotation_error_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle ``[...]`` in degrees between the rotations of camera-to-world matrices ``a`` and ``b`` ``[..., 4, 4]``."""
    relative = a[..., :3, :3].transpose(-1, -2) @ b[..., :3, :3]
    cos = ((relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos))


class PoseRefinement(nn.Module):
    """Learnable updates of ``V`` starting poses ``c2w [V, 4, 4]``; ``forward()`` gives the refined poses."""

    def __init__(self, c2w: torch.Tensor):
        super().__init__()
        self.register_buffer("start", c2w.detach().clone())
        self.rotation = nn.Parameter(torch.zeros(c2w.shape[0], 3, device=c2w.device))
        self.translation = nn.Parameter(torch.zeros(c2w.shape[0], 3, device=c2w.device))

    def forward(self) -> torch.Tensor:
        rot = self.start[:, :3, :3] @ axis_angle_to_matrix(self.rotation)
        top = torch.cat([rot, (self.start[:, :3, 3] + self.translation)[..., None]], -1)
        return torch.cat([top, self.start[:, 3:]], 1)


class PixelBank:
    """Every pixel of the input views, ready to become rays for any pose of its view."""

    def __init__(self, images: torch.Tensor, cameras: Sequence[Intrinsics], device):
        self.directions = torch.stack([camera_directions(c, device=device).reshape(-1, 3) for c in cameras])  # [V, P, 3]
        self.rgba = images.to(device).reshape(images.shape[0], -1, 4)  # [V, P, 4]

    @property
    def count(self) -> int:
        return self.rgba.shape[0] * self.rgba.shape[1]

    def sample(self, count: int, c2w: torch.Tensor, generator: torch.Generator) -> RayBatch:
        """``count`` random pixels as world rays through poses ``c2w [V, 4, 4]`` (differentiable in ``c2w``)."""
        pixels = self.rgba.shape[1]
        pick = torch.randint(self.count, (count,), generator=generator, device=self.rgba.device)
        view, pixel = pick // pixels, pick % pixels
        rot = c2w[view, :3, :3]
        directions = (rot @ self.directions[view, pixel][..., None]).squeeze(-1)
        directions = directions / directions.norm(dim=-1, keepdim=True)
        return RayBatch(c2w[view, :3, 3], directions, self.rgba[view, pixel])


def candidate_poses(azimuths: int = 12, elevations: Sequence[float] = (10.0, 30.0, 50.0, 70.0),
                    radii: Sequence[float] = (2.0,)) -> torch.Tensor:
    """Look-at poses ``[N, 4, 4]`` at the scene centre over a grid of azimuths, elevations (degrees) and distances."""
    poses = [look_at(r * spherical_direction(el, 360.0 * k / azimuths)) for r in radii for el in elevations for k in range(azimuths)]
    return torch.tensor(np.stack(poses), dtype=torch.float32)


def perturb_pose(c2w: torch.Tensor, degrees: float, generator: torch.Generator, translation: float = 0.0) -> torch.Tensor:
    """``c2w [4, 4]`` turned by ``degrees`` about a random axis (in its own frame), shifted by ``translation``."""
    axis = torch.randn(3, generator=generator)
    axis = axis / axis.norm()
    shift = torch.randn(3, generator=generator)
    out = c2w.clone()
    out[:3, :3] = c2w[:3, :3] @ axis_angle_to_matrix(axis * math.radians(degrees))
    out[:3, 3] = c2w[:3, 3] + translation * shift / shift.norm()
    return out
