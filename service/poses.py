"""Cameras of render requests: an orbit around the scene centre or an explicit 4x4 pose, validated.

Conventions are the dataset's (``model.data.cameras``): the world is Z-up, orbit cameras look at
the scene centre with the world's +Z projected onto the image as up, and matrices are
camera-to-world in the OpenGL convention (the camera looks down its -Z axis, +Y up, +X right).
"""

from __future__ import annotations

import math

import numpy as np

from model.data.cameras import look_at, spherical_direction
from model.nerf.rays import Intrinsics
from model.nerf.scene import SceneBox

ORTHONORMAL_TOLERANCE = 1e-3


class PoseError(ValueError):
    """A camera request that cannot be rendered; the message says why and what to send instead."""


def _outside(scene: SceneBox, position: np.ndarray) -> bool:
    return bool(np.any(position < np.asarray(scene.min)) or np.any(position > np.asarray(scene.max)))


def scene_centre(scene: SceneBox) -> np.ndarray:
    return 0.5 * (np.asarray(scene.min) + np.asarray(scene.max))


def orbit_pose(scene: SceneBox, azimuth: float, elevation: float, radius: float) -> np.ndarray:
    """Look-at pose ``[4, 4]`` at ``radius`` from the scene centre, ``azimuth``/``elevation`` in degrees."""
    centre = scene_centre(scene)
    eye = centre + radius * spherical_direction(elevation, azimuth)
    if not _outside(scene, eye):
        raise PoseError(f"a camera at radius {radius:g} is inside the scene box {scene.to_aabb()}; use a larger radius "
                        f"(at least {0.5 * math.sqrt(sum(s * s for s in scene.size)):.3g} is outside from every direction)")
    return look_at(eye, centre)


def parse_pose(text: str, scene: SceneBox) -> np.ndarray:
    """A camera-to-world pose from 16 comma-separated numbers (row-major 4x4), checked by :func:`check_pose`."""
    parts = [p for p in text.replace(" ", "").split(",")]
    try:
        values = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise PoseError("pose must be 16 comma-separated numbers (a row-major 4x4 camera-to-world matrix)") from None
    if values.size != 16:
        raise PoseError(f"pose must have 16 numbers (a row-major 4x4 matrix), got {values.size}")
    return check_pose(values.reshape(4, 4), scene)


def check_pose(pose: np.ndarray, scene: SceneBox) -> np.ndarray:
    """A 4x4 camera-to-world ``pose`` as float64 if it is usable: finite, bottom row ``0,0,0,1``,
    rotation orthonormal with determinant +1, camera outside the scene box (else ``PoseError``)."""
    pose = np.asarray(pose, dtype=np.float64)
    if not np.isfinite(pose).all():
        raise PoseError("pose has NaN or infinite entries; every entry must be a finite number")
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise PoseError(f"the pose's bottom row must be 0,0,0,1, got {pose[3].tolist()}")
    rot = pose[:3, :3]
    error = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if error > ORTHONORMAL_TOLERANCE or np.linalg.det(rot) < 0:
        raise PoseError(f"the pose's rotation (upper-left 3x3) must be orthonormal with determinant +1 "
                        f"(largest error of R^T R - I: {error:.3g}, determinant {np.linalg.det(rot):.3g}); "
                        "no scale or shear, no mirroring")
    if not _outside(scene, pose[:3, 3]):
        raise PoseError(f"the camera position {pose[:3, 3].tolist()} is inside the scene box {scene.to_aabb()}; "
                        "place the camera outside it")
    return pose


def intrinsics(width: int, height: int, fov_degrees: float) -> Intrinsics:
    """A centred pinhole of the given horizontal field of view, square pixels."""
    return Intrinsics.from_fov(width, height, math.radians(fov_degrees))


def horizontal_fov_degrees(camera: Intrinsics) -> float:
    return math.degrees(2.0 * math.atan(0.5 * camera.width / camera.fx))
