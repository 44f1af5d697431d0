"""Ground-truth RGBA renders of a :class:`~model.data.meshes.RenderMesh` by CPU ray casting.

Rays come from :func:`model.nerf.rays.pixel_rays` (the same cameras a NeRF is trained with) and are
intersected with **embreex** (Intel Embree's Python binding, the ray caster trimesh itself uses:
several million rays per second on one core here), which returns the hit triangle and its
barycentric coordinates directly.

- Antialiasing: ``supersample x supersample`` rays per pixel on a regular sub-pixel grid. Alpha
  is the covered fraction; colour is the mean over covered sub-rays (straight alpha), so a
  partly covered edge pixel keeps the object's colour rather than fading to the background.
- Albedo: material colour x bilinear, wrapping texture lookup at the interpolated UV x the
  interpolated corner colour.
- Shading: view-independent Lambertian with fixed world-space lights plus ambient, computed in
  linear RGB and encoded back to sRGB. Normals are the hit triangle's, turned towards the camera
  (two-sided), so open or inconsistently wound meshes shade correctly. View independence keeps
  the images fittable by a NeRF.
"""

from __future__ import annotations

import numpy as np
import torch
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from tqdm import tqdm

from model.data.meshes import RenderMesh
from model.nerf.rays import Intrinsics, pixel_rays

DEFAULT_SUPERSAMPLE = 2
AMBIENT = 0.30
# (direction towards the light, intensity); the key light is above the front-left (fronts face -Y).
LIGHTS = (
    ((-0.45, -0.65, 0.62), 0.60),
    ((0.70, 0.35, 0.35), 0.30),
    ((0.0, 0.0, -1.0), 0.12),
)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1.0 / 2.4) - 0.055)


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with wrap-around of ``texture [H, W, C]`` at ``uv [N, 2]`` (v = 1 is the top row)."""
    height, width = texture.shape[:2]
    x = uv[:, 0] * width - 0.5
    y = (1.0 - uv[:, 1]) * height - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 = x0.astype(np.int64) % width
    y0 = y0.astype(np.int64) % height
    x1, y1 = (x0 + 1) % width, (y0 + 1) % height
    top = texture[y0, x0] * (1.0 - fx) + texture[y0, x1] * fx
    bottom = texture[y1, x0] * (1.0 - fx) + texture[y1, x1] * fx
    return top * (1.0 - fy) + bottom * fy


class RayCaster:
    """An Embree scene of one mesh, shading hits with the mesh's materials."""

    def __init__(self, mesh: RenderMesh):
        if len(mesh.faces) == 0:
            raise ValueError("the mesh has no triangles to render")
        self.mesh = mesh
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            self.scene,
            np.ascontiguousarray(mesh.vertices, dtype=np.float32),
            np.ascontiguousarray(mesh.faces, dtype=np.int32),
        )
        normals = np.cross(mesh.triangles[:, 1] - mesh.triangles[:, 0], mesh.triangles[:, 2] - mesh.triangles[:, 0])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        self.face_normals = np.where(length > 0, normals / np.maximum(length, 1e-30), 0.0).astype(np.float32)
        self.lights = np.array([d for d, _ in LIGHTS], dtype=np.float32)
        self.lights /= np.linalg.norm(self.lights, axis=1, keepdims=True)
        self.light_power = np.array([p for _, p in LIGHTS], dtype=np.float32)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear RGB ``[N, 3]`` and coverage ``[N]`` (0 or 1) of rays ``[N, 3]``."""
        hit = self.scene.run(
            np.ascontiguousarray(origins, dtype=np.float32), np.ascontiguousarray(directions, dtype=np.float32), output=1
        )
        face = hit["primID"]
        covered = face >= 0
        rgb = np.zeros((len(face), 3), dtype=np.float32)
        if covered.any():
            rgb[covered] = self._shade(face[covered], hit["u"][covered], hit["v"][covered], directions[covered])
        return rgb, covered.astype(np.float32)

    def _shade(self, face: np.ndarray, u: np.ndarray, v: np.ndarray, directions: np.ndarray) -> np.ndarray:
        mesh = self.mesh
        # Embree's barycentrics: hit = (1 - u - v) * p0 + u * p1 + v * p2.
        weights = np.stack([1.0 - u - v, u, v], axis=-1)[:, :, None]
        albedo = (mesh.corner_colour[face] * weights).sum(axis=1)
        material = mesh.face_material[face]
        for index in np.unique(material):
            chosen = material == index
            spec = mesh.materials[index]
            colour = np.asarray(spec.colour, dtype=np.float32)
            if spec.texture is not None:
                uv = (mesh.corner_uv[face[chosen]] * weights[chosen]).sum(axis=1)
                colour = colour * sample_texture(spec.texture, uv)
            albedo[chosen] *= colour
        normals = self.face_normals[face]
        normals = np.where((normals * directions).sum(axis=1, keepdims=True) > 0, -normals, normals)
        irradiance = AMBIENT + (np.clip(normals @ self.lights.T, 0.0, None) * self.light_power).sum(axis=1)
        return srgb_to_linear(albedo[:, :3]) * irradiance[:, None]

    def render(self, origins: np.ndarray, directions: np.ndarray, supersample: int = DEFAULT_SUPERSAMPLE) -> np.ndarray:
        """One view as straight-alpha 8-bit RGBA ``[H, W, 4]`` from its sub-pixel rays ``[H*s, W*s, 3]``."""
        s = int(supersample)
        height, width = origins.shape[0] // s, origins.shape[1] // s
        rgb, covered = self.cast(origins.reshape(-1, 3), directions.reshape(-1, 3))
        # Sub-ray (row, col) belongs to pixel (row // s, col // s).
        rgb = rgb.reshape(height, s, width, s, 3).sum(axis=(1, 3))
        alpha = covered.reshape(height, s, width, s).sum(axis=(1, 3))
        colour = np.where(alpha[..., None] > 0, rgb / np.maximum(alpha, 1.0)[..., None], 0.0)
        rgba = np.concatenate([linear_to_srgb(colour), (alpha / (s * s))[..., None]], axis=-1)
        return np.round(rgba * 255.0).astype(np.uint8)


def render_views(
    mesh: RenderMesh,
    c2w: np.ndarray,
    width: int,
    height: int,
    focal: float,
    supersample: int = DEFAULT_SUPERSAMPLE,
    desc: str = "rendering",
) -> np.ndarray:
    """Render every pose of ``c2w [V, 4, 4]`` (OpenGL convention); returns 8-bit straight-alpha RGBA ``[V, H, W, 4]``.

    Sub-pixel rays are ``pixel_rays`` at ``supersample`` times the resolution and focal length,
    which puts ``s x s`` ray centres on a regular grid inside each pixel.
    """
    caster = RayCaster(mesh)
    s = int(supersample)
    # Rays of an identity camera, turned by each pose below: the same rays pixel_rays gives for
    # that pose, built once and rotated into reused buffers (fresh memory is slow to fault in).
    _, local = pixel_rays(torch.eye(4, dtype=torch.float64), Intrinsics.centred(width * s, height * s, focal * s))
    local = local.numpy().astype(np.float32)
    directions, origins = np.empty_like(local), np.empty_like(local)
    views = np.zeros((len(c2w), height, width, 4), dtype=np.uint8)
    for index, pose in enumerate(tqdm(np.asarray(c2w, dtype=np.float32), desc=desc, unit="view", leave=False)):
        np.matmul(local, pose[:3, :3].T, out=directions)
        origins[...] = pose[:3, 3]
        views[index] = caster.render(origins, directions, s)
    return views
