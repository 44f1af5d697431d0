"""Camera poses shared by every object of every dataset.

Conventions (the scene side of the on-disk format):

- The world is Z-up. Each object is normalised so its bounding box is centred at the origin with
  its longest side 0.9, inside the scene box ``[-0.5, 0.5]^3``. Furniture faces -Y.
- Cameras sit at ``RADIUS = 2.0`` from the origin and look at it, with a horizontal field of view
  ``CAMERA_ANGLE_X = 2 * atan(0.5)``: the box's bounding sphere (radius ``sqrt(3)/2``) subtends
  25.7 degrees from there, inside the 26.6 degree half-angle, so the whole box is always in view.
- Matrices are 4x4 camera-to-world in the OpenGL convention of ``model.nerf.rays``: the camera looks
  down its -Z axis, +Y up, +X right. The camera's up vector is the world's +Z projected onto the
  image plane, so horizons stay level.
- Training poses lie on a Fibonacci lattice of the upper hemisphere: ``V`` points with heights
  ``z_i = (i + 0.5) / V`` (equal-area bands, so density is uniform over the hemisphere) and
  golden-angle azimuths. It is deterministic, defined for any ``V`` (91 by default, as in ABO),
  and never lands exactly on the pole, where a Z-up look-at would be degenerate.
- Evaluation poses are 12 fixed poses, the same for every object: three elevation rings (15, 40
  and 63 degrees) of four azimuths 90 degrees apart, each ring turned so that every pose lies at
  least 5.9 degrees from all poses of the default 91-view training set (whose neighbours are
  about 15 degrees apart), i.e. in between them.
"""

from __future__ import annotations

import math

import numpy as np

RADIUS = 2.0
CAMERA_ANGLE_X = 2.0 * math.atan(0.5)
DEFAULT_VIEWS = 91

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
# Evaluation rings: (elevation, azimuth offset) in degrees, offsets found by search against the
# 91-view training set to maximise the distance to the nearest training pose.
_TEST_RINGS = ((15.0, 36.0), (40.0, 77.0), (63.0, 45.0))


def look_at(eye: np.ndarray, target: np.ndarray | None = None, up: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world matrix ``[4, 4]`` (OpenGL convention) for a camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    target = np.zeros(3) if target is None else np.asarray(target, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    back = eye - target
    back = back / np.linalg.norm(back)
    right = np.cross(up, back)
    norm = np.linalg.norm(right)
    if norm < 1e-8:
        raise ValueError(f"camera at {eye.tolist()} looks along the up vector {up.tolist()}; choose another up vector")
    right = right / norm
    cam_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, back, eye
    return c2w


def fibonacci_hemisphere(count: int) -> np.ndarray:
    """``count`` unit vectors spread uniformly over the upper hemisphere (z > 0), ``[count, 3]``."""
    if count < 1:
        raise ValueError(f"need at least one view, got {count}")
    i = np.arange(count, dtype=np.float64)
    z = (i + 0.5) / count
    r = np.sqrt(1.0 - z * z)
    phi = i * _GOLDEN_ANGLE
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def spherical_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector at the given elevation above the XY plane and azimuth from +X towards +Y."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def poses_from_directions(directions: np.ndarray, radius: float = RADIUS) -> np.ndarray:
    """Look-at poses ``[N, 4, 4]`` at ``radius`` along each direction, looking at the origin."""
    return np.stack([look_at(radius * d) for d in directions]) if len(directions) else np.zeros((0, 4, 4))


def training_poses(count: int = DEFAULT_VIEWS, radius: float = RADIUS) -> np.ndarray:
    """The ``count`` training poses ``[count, 4, 4]`` on the Fibonacci hemisphere."""
    return poses_from_directions(fibonacci_hemisphere(count), radius)


def evaluation_poses(radius: float = RADIUS) -> np.ndarray:
    """The 12 fixed evaluation poses ``[12, 4, 4]``, identical for every object."""
    directions = [
        spherical_direction(elevation, offset + 90.0 * k) for elevation, offset in _TEST_RINGS for k in range(4)
    ]
    return poses_from_directions(np.stack(directions), radius)
