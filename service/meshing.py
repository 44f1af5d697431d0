"""Meshes of generated NeRFs: marching cubes, decimation, colours, and UV-atlas texture baking.

* Geometry: the NeRF's density (zeroed where its occupancy grid is empty, as the renderer sees it)
  through ``model.nerf.mesh.extract_mesh`` (scikit-image marching cubes) over the grid's tight box.
* Decimation to a face budget: ``fast_simplification`` (quadric edge collapse, the fast-simplify C
  library; orders of magnitude faster than a Python simplifier).
* Colours are the colour net's at each surface point **seen head-on**: the view direction is the
  opposite of the outward surface normal (the ray of a camera facing that surface). Per vertex, or
  baked into a texture over a UV atlas made by ``xatlas`` (the xatlas library's charts and packing),
  one colour per texel at the surface point the texel maps to; texels outside every chart take the
  nearest chart texel's colour so that texture filtering never bleeds background into the seams.
* Up axis: the world is Z-up (the dataset's convention, ``model.data.cameras``); GLB is written
  Y-up as glTF requires (``model.nerf.mesh.mesh_bytes``), PLY and OBJ keep Z-up.
"""

from __future__ import annotations

import io
import zipfile

import cv2
import fast_simplification
import numpy as np
import torch
import trimesh
import xatlas
from PIL import Image
from scipy.ndimage import distance_transform_edt

from model.nerf.fields import Field, FieldParams, world_density
from model.nerf.mesh import extract_mesh, mesh_bytes
from model.nerf.occupancy import OccupancyGrid
from model.nerf.scene import SceneBox

DEFAULT_UV_FACES = 10_000
_CHUNK = 1 << 16

MEDIA_TYPES = {"glb": "model/gltf-binary", "ply": "application/ply", "obj": "model/obj", "zip": "application/zip"}


def nerf_geometry(params: FieldParams, field: Field, grid: OccupancyGrid, scene: SceneBox, resolution: int,
                  min_component: float = 0.0) -> trimesh.Trimesh:
    """The NeRF's iso-surface over its occupied box (world coordinates, no colours), without
    connected pieces smaller than ``min_component`` of the largest's area; empty when the grid is
    empty or no density crosses the threshold."""
    box = grid.tight_box()
    if box is None:
        return trimesh.Trimesh()
    density = world_density(params, field, scene)
    return extract_mesh(lambda points: density(points) * grid.lookup(points), box[0], box[1], resolution=resolution,
                        min_component_fraction=min_component)


def decimate(mesh: trimesh.Trimesh, target_faces: int) -> trimesh.Trimesh:
    """``mesh`` simplified to at most about ``target_faces`` faces (unchanged when it has fewer)."""
    if len(mesh.faces) <= target_faces:
        return mesh
    points, faces = fast_simplification.simplify(
        np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.int64),
        target_reduction=1.0 - target_faces / len(mesh.faces))
    simplified = trimesh.Trimesh(vertices=points, faces=faces, process=True)
    simplified.update_faces(simplified.nondegenerate_faces())
    simplified.remove_unreferenced_vertices()
    return simplified


@torch.no_grad()
def surface_colors(params: FieldParams, field: Field, scene: SceneBox, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """RGB uint8 ``[N, 3]`` of the colour net at world ``points [N, 3]`` seen along ``-normals [N, 3]``."""
    out = np.zeros((len(points), 3), dtype=np.uint8)
    for start in range(0, len(points), _CHUNK):
        pts = torch.from_numpy(np.array(points[start:start + _CHUNK], dtype=np.float32))
        view = -torch.from_numpy(np.array(normals[start:start + _CHUNK], dtype=np.float32))
        view = view / view.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        _, geo = field.density(params, scene.to_unit(pts)[None])
        rgb = field.color_from_view_term(params, geo, field.view_term(params, view[None]))[0]
        out[start:start + len(pts)] = (rgb.float().nan_to_num(0.0).clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()
    return out


def color_vertices(mesh: trimesh.Trimesh, params: FieldParams, field: Field, scene: SceneBox) -> trimesh.Trimesh:
    rgb = surface_colors(params, field, scene, np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals))
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1))
    return mesh


def _rasterise_faces(uv: np.ndarray, faces: np.ndarray, size: int) -> np.ndarray:
    """Face index covering each texel ``[size, size]`` (-1 where none), texel rows top to bottom."""
    ids = np.full((size, size), -1, dtype=np.int32)
    shift = 4  # sub-pixel bits of cv2's fixed-point vertices
    corners = np.stack([uv[:, 0] * size - 0.5, (1.0 - uv[:, 1]) * size - 0.5], axis=-1)
    fixed = np.round(corners * (1 << shift)).astype(np.int32)[faces]  # [F, 3, 2]
    for index, triangle in enumerate(fixed):
        cv2.fillConvexPoly(ids, triangle, int(index), lineType=cv2.LINE_8, shift=shift)
    return ids


def _barycentric(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates ``[N, 3]`` of 2-D points ``p [N, 2]`` in triangles ``(a, b, c)``,
    clamped onto the triangle (texels on a chart's rim map to its edge)."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    denom = d00 * d11 - d01 * d01
    safe = np.where(np.abs(denom) > 1e-20, denom, 1.0)
    v = np.where(np.abs(denom) > 1e-20, (d11 * d20 - d01 * d21) / safe, 1.0 / 3.0)
    w = np.where(np.abs(denom) > 1e-20, (d00 * d21 - d01 * d20) / safe, 1.0 / 3.0)
    bary = np.clip(np.stack([1.0 - v - w, v, w], axis=-1), 0.0, None)
    return bary / bary.sum(-1, keepdims=True).clip(1e-12)


def bake_uv_texture(mesh: trimesh.Trimesh, params: FieldParams, field: Field, scene: SceneBox, size: int) -> trimesh.Trimesh:
    """``mesh`` re-indexed over an xatlas UV atlas, with a ``size`` x ``size`` texture of the NeRF's colour."""
    vmapping, indices, uv = xatlas.parametrize(np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.uint32))
    vertices = np.asarray(mesh.vertices)[vmapping]
    normals = np.asarray(mesh.vertex_normals)[vmapping]
    faces = indices.astype(np.int64)
    ids = _rasterise_faces(uv, faces, size)
    rows, cols = np.nonzero(ids >= 0)
    face = faces[ids[rows, cols]]  # [N, 3] vertex indices
    pixel_uv = np.stack([(cols + 0.5) / size, 1.0 - (rows + 0.5) / size], axis=-1)
    bary = _barycentric(pixel_uv, uv[face[:, 0]], uv[face[:, 1]], uv[face[:, 2]])
    points = np.einsum("nk,nkd->nd", bary, vertices[face])
    point_normals = np.einsum("nk,nkd->nd", bary, normals[face])
    texture = np.zeros((size, size, 3), dtype=np.uint8)
    texture[rows, cols] = surface_colors(params, field, scene, points, point_normals)
    if len(rows):
        _, (near_r, near_c) = distance_transform_edt(ids < 0, return_indices=True)
        texture = texture[near_r, near_c]
    material = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(texture), metallicFactor=0.0, roughnessFactor=1.0)
    baked = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    baked.visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    return baked


def encode(mesh: trimesh.Trimesh, format: str, texture: str) -> tuple[bytes, str, str]:
    """``(data, media type, file extension)`` of ``mesh``: GLB/PLY/OBJ, or for a textured OBJ a zip
    of ``mesh.obj``, ``material.mtl`` and the texture PNG (OBJ keeps its texture in side files)."""
    if texture == "uv" and format == "obj":
        obj_text, files = trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_texture=True,
                                                          return_texture=True, mtl_name="material.mtl")
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
            archive.writestr("mesh.obj", obj_text)
            for name, data in files.items():
                archive.writestr(name, data)
        return buffer.getvalue(), MEDIA_TYPES["zip"], "zip"
    return mesh_bytes(mesh, format), MEDIA_TYPES[format], format
