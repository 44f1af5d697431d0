"""Coloured, textured triangle meshes as the ground-truth renderer sees them, and loading them from files.

A :class:`RenderMesh` is a triangle soup with one material per face, UVs and colours per face
corner (so seams and per-face colours need no vertex splitting), and materials holding a base
colour and an optional texture image. The albedo at a surface point is
``material.colour * texture(uv) * corner colour``.

Files (OBJ+MTL, GLB/glTF, PLY, anything trimesh reads) are loaded with **trimesh**, the
well-kept standard Python mesh library, which resolves MTL files and texture images next to the
model. Material rules:

- MTL (trimesh ``SimpleMaterial``): a ``map_Kd`` texture replaces ``Kd``, as Sweet Home 3D
  shows it; a texture file the MTL names but that is absent is logged and the ``Kd`` colour is
  used instead.
- glTF (``PBRMaterial``): ``baseColorTexture`` times ``baseColorFactor``, as the glTF spec says.
- Vertex or face colours (``ColorVisuals``, common in PLY) become corner colours.
- Everything is opaque: material transparency is ignored.

Conventions: the world is Z-up; :func:`y_up_to_z_up` turns Y-up sources (Sweet Home 3D, GLB, most
OBJ) upright, mapping their front (+Z) to -Y. :func:`normalise` centres the bounding box at
the origin and scales the longest side to ``OBJECT_SIZE`` = 0.9, inside the scene box
``[-0.5, 0.5]^3``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

log = logging.getLogger(__name__)

OBJECT_SIZE = 0.9
MAX_TEXTURE_SIZE = 1024

# Y-up to Z-up: (x, y, z) -> (x, -z, y); the Y-up front (+Z) becomes -Y.
_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@dataclass
class Material:
    """A base colour (sRGB RGBA in [0, 1]) and an optional texture ``[H, W, 4]`` float32 sRGB image.

    Texture row 0 is the top of the image (v = 1); UVs wrap around (repeat).
    """

    name: str
    colour: np.ndarray
    texture: np.ndarray | None = None


@dataclass
class RenderMesh:
    """Triangles with per-face materials and per-corner UVs and colours.

    ``vertices [N, 3]`` float64, ``faces [F, 3]`` int64, ``face_material [F]`` int64 indexing
    ``materials``, ``corner_uv [F, 3, 2]`` float32, ``corner_colour [F, 3, 4]`` float32 sRGB.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_material: np.ndarray
    corner_uv: np.ndarray
    corner_colour: np.ndarray
    materials: list[Material]

    @property
    def triangles(self) -> np.ndarray:
        """Corner positions ``[F, 3, 3]``."""
        return self.vertices[self.faces]

    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box ``[2, 3]`` of the vertices used by faces."""
        used = self.vertices[np.unique(self.faces)]
        return np.stack([used.min(axis=0), used.max(axis=0)])

    def transformed(self, matrix: np.ndarray, offset: np.ndarray | None = None) -> RenderMesh:
        """A copy with vertices mapped to ``matrix @ v + offset``; a reflection keeps faces outward."""
        vertices = self.vertices @ np.asarray(matrix, dtype=np.float64).T
        if offset is not None:
            vertices = vertices + offset
        if np.linalg.det(matrix) < 0:
            flip = [0, 2, 1]
            return replace(
                self,
                vertices=vertices,
                faces=self.faces[:, flip],
                corner_uv=self.corner_uv[:, flip],
                corner_colour=self.corner_colour[:, flip],
            )
        return replace(self, vertices=vertices)

    def mean_face_colours(self) -> np.ndarray:
        """An 8-bit RGBA colour per face (material colour, mean texture colour, mean corner colour)."""
        base = np.stack([m.colour for m in self.materials])
        texture_mean = np.stack(
            [np.ones(4) if m.texture is None else m.texture.reshape(-1, 4).mean(axis=0) for m in self.materials]
        )
        colour = base[self.face_material] * texture_mean[self.face_material] * self.corner_colour.mean(axis=1)
        return np.clip(np.round(colour * 255.0), 0, 255).astype(np.uint8)

    def to_trimesh(self) -> trimesh.Trimesh:
        """Geometry with per-face mean colours, for writing the ground-truth ``mesh.ply``."""
        return trimesh.Trimesh(
            vertices=self.vertices, faces=self.faces, face_colors=self.mean_face_colours(), process=False
        )


def concatenate(meshes: list[RenderMesh]) -> RenderMesh:
    """One mesh holding all parts; material lists are appended in order."""
    if not meshes:
        raise ValueError("nothing to concatenate: the model has no triangle geometry")
    vertex_offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    material_offsets = np.cumsum([0] + [len(m.materials) for m in meshes[:-1]])
    return RenderMesh(
        vertices=np.concatenate([m.vertices for m in meshes]),
        faces=np.concatenate([m.faces + o for m, o in zip(meshes, vertex_offsets)]),
        face_material=np.concatenate([m.face_material + o for m, o in zip(meshes, material_offsets)]),
        corner_uv=np.concatenate([m.corner_uv for m in meshes]),
        corner_colour=np.concatenate([m.corner_colour for m in meshes]),
        materials=[material for m in meshes for material in m.materials],
    )


def solid_mesh(vertices: np.ndarray, faces: np.ndarray, material: Material, corner_uv: np.ndarray | None = None) -> RenderMesh:
    """A single-material mesh with white corner colours (and zero UVs unless given)."""
    faces = np.asarray(faces, dtype=np.int64)
    count = len(faces)
    return RenderMesh(
        vertices=np.asarray(vertices, dtype=np.float64),
        faces=faces,
        face_material=np.zeros(count, dtype=np.int64),
        corner_uv=np.zeros((count, 3, 2), np.float32) if corner_uv is None else np.asarray(corner_uv, np.float32),
        corner_colour=np.ones((count, 3, 4), dtype=np.float32),
        materials=[material],
    )


def y_up_to_z_up(mesh: RenderMesh) -> RenderMesh:
    """Rotate a Y-up mesh upright in the Z-up world (its +Z front ends up facing -Y)."""
    return mesh.transformed(_Y_UP_TO_Z_UP)


def normalise(mesh: RenderMesh, size: float = OBJECT_SIZE) -> RenderMesh:
    """Centre the bounding box at the origin and scale uniformly so its longest side is ``size``."""
    lo, hi = mesh.bounds()
    extent = float((hi - lo).max())
    if not np.isfinite(extent) or extent <= 0.0:
        raise ValueError(f"the mesh is degenerate (bounding box {lo.tolist()} to {hi.tolist()}); it cannot be normalised")
    scale = size / extent
    return mesh.transformed(np.eye(3) * scale, -0.5 * (lo + hi) * scale)


def image_to_texture(image: Image.Image, max_size: int = MAX_TEXTURE_SIZE) -> np.ndarray:
    """A Pillow image as a float32 sRGB RGBA array in [0, 1], shrunk to at most ``max_size`` per side."""
    image = image.convert("RGBA")
    if max(image.size) > max_size:
        # Ground truth is rendered at a few hundred pixels: 4k textures would only cost memory.
        image.thumbnail((max_size, max_size), Image.Resampling.LANCZOS)
    return np.asarray(image, dtype=np.float32) / 255.0


class _RecordingResolver(trimesh.resolvers.FilePathResolver):
    """Resolves files next to the model, matching names case-insensitively, and records the ones missing.

    Models made on case-insensitive file systems often name ``Wood.JPG`` for ``wood.jpg``.
    """

    def __init__(self, source: Path):
        super().__init__(str(source))
        self.folder = source.parent
        self.missing: list[str] = []

    def get(self, name: str) -> bytes:
        try:
            return super().get(name)
        except (FileNotFoundError, OSError):
            wanted = Path(name.replace("\\", "/"))
            parent = self.folder / wanted.parent
            if parent.is_dir():
                for candidate in parent.iterdir():
                    if candidate.name.lower() == wanted.name.lower() and candidate.is_file():
                        return candidate.read_bytes()
            self.missing.append(name)
            raise


def _material_from_trimesh(material, name: str) -> Material:
    """Base colour and texture of a trimesh material (see the module docstring for the rules)."""
    if isinstance(material, trimesh.visual.material.PBRMaterial):
        factor = material.baseColorFactor
        colour = np.ones(4) if factor is None else np.asarray(factor, dtype=np.float64) / 255.0
        image = material.baseColorTexture
    else:
        image = getattr(material, "image", None)
        diffuse = getattr(material, "diffuse", None)
        colour = np.ones(4) if image is not None or diffuse is None else np.asarray(diffuse, dtype=np.float64) / 255.0
    texture = None if image is None else image_to_texture(image)
    return Material(name=name, colour=colour, texture=texture)


def _part_from_trimesh(part: trimesh.Trimesh, name: str) -> RenderMesh:
    """One trimesh geometry (transforms already applied) as a single-material render mesh."""
    faces = np.asarray(part.faces, dtype=np.int64)
    visual = part.visual
    if isinstance(visual, trimesh.visual.TextureVisuals):
        material = _material_from_trimesh(visual.material, name) if visual.material is not None else None
        uv = visual.uv
        corner_uv = None if uv is None or len(uv) != len(part.vertices) else np.asarray(uv, np.float32)[faces]
        if material is None:
            material = Material(name=name, colour=np.ones(4))
        if material.texture is not None and corner_uv is None:
            log.warning("part %r has a texture but no UVs; using its mean colour", name)
            material = Material(name=name, colour=material.texture.reshape(-1, 4).mean(axis=0), texture=None)
        return solid_mesh(part.vertices, faces, material, corner_uv)
    mesh = solid_mesh(part.vertices, faces, Material(name=name, colour=np.ones(4)))
    if isinstance(visual, trimesh.visual.ColorVisuals) and visual.defined:
        if visual.kind == "face":
            colours = np.asarray(visual.face_colors, dtype=np.float32) / 255.0
            mesh.corner_colour = np.repeat(colours[:, None, :], 3, axis=1)
        else:
            mesh.corner_colour = (np.asarray(visual.vertex_colors, dtype=np.float32) / 255.0)[faces]
    return mesh


def load_mesh_file(path: Path) -> tuple[RenderMesh, list[str]]:
    """Load every triangle geometry of a mesh file into one render mesh in the file's own axes.

    Returns the mesh and the texture file names the file refers to but that could not be found.
    Raises ``ValueError`` when the file holds no triangles.
    """
    path = Path(path)
    resolver = _RecordingResolver(path)
    try:
        scene = trimesh.load_scene(str(path), resolver=resolver)
    except Exception as error:  # trimesh raises many kinds for unreadable files
        raise ValueError(f"could not read {path}: {error}; check that it is a valid OBJ/GLB/PLY file") from error
    parts = [
        _part_from_trimesh(geometry, str(geometry.metadata.get("name", "part")))
        for geometry in scene.dump()
        if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces)
    ]
    if not parts:
        raise ValueError(f"{path} holds no triangles (point clouds and lines cannot be rendered)")
    missing = sorted(set(resolver.missing))
    if missing:
        log.warning("%s: texture file(s) %s not found; using the material colour instead", path, ", ".join(missing))
    return concatenate(parts), missing
