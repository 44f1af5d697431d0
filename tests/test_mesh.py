import io

import numpy as np
import pytest
import torch
import trimesh

from model.nerf.mesh import SUPPORTED_FORMATS, density_grid, export_mesh, extract_mesh, mesh_bytes
from model.eval.metrics import mesh_chamfer

BOX_MIN = torch.tensor([-0.5, -0.5, -0.5])
BOX_MAX = torch.tensor([0.5, 0.5, 0.5])
RES = 48
CELL = 1.0 / (RES - 1)
RADIUS = 0.3


def step_sphere(points):
    return 100.0 * (points.norm(dim=-1) < RADIUS).float()


def smooth_sphere(points):
    # Linear in the radius and crossing the threshold 10 at RADIUS, so linear interpolation in
    # marching cubes is exact up to the sphere's curvature within a cell.
    return 10.0 + 200.0 * (RADIUS - points.norm(dim=-1))


def position_color(points):
    return (points + 0.5).clamp(0, 1)


@pytest.fixture(scope="module")
def coloured_sphere():
    return extract_mesh(step_sphere, BOX_MIN, BOX_MAX, resolution=RES, color_fn=position_color)


def test_step_density_sphere(coloured_sphere):
    mesh = coloured_sphere
    assert not mesh.is_empty
    assert mesh.is_watertight
    assert mesh.volume > 0  # outward normals
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert np.all(np.abs(radius - RADIUS) < CELL)
    assert mesh_chamfer(mesh, trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)) < CELL


def test_smooth_density_sphere_is_accurate():
    mesh = extract_mesh(smooth_sphere, BOX_MIN, BOX_MAX, resolution=RES)
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert np.all(np.abs(radius - RADIUS) < 0.1 * CELL)
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * RADIUS**3, rel=0.01)
    assert mesh_chamfer(mesh, trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)) < 0.5 * CELL


def test_world_coordinates_in_an_anisotropic_box():
    centre = torch.tensor([0.1, 0.0, -0.1])
    lo, hi = torch.tensor([-0.3, -0.4, -0.5]), torch.tensor([0.5, 0.3, 0.2])
    mesh = extract_mesh(lambda p: 10.0 + 200.0 * (0.2 - (p - centre).norm(dim=-1)), lo, hi, resolution=40)
    radius = np.linalg.norm(mesh.vertices - centre.numpy(), axis=1)
    assert np.all(np.abs(radius - 0.2) < 1e-3)
    assert np.allclose(mesh.bounds, [[-0.1, -0.2, -0.3], [0.3, 0.2, 0.1]], atol=1e-3)


def test_chunking_does_not_change_the_result(coloured_sphere):
    small = extract_mesh(step_sphere, BOX_MIN, BOX_MAX, resolution=RES, color_fn=position_color, chunk=1000)
    assert np.array_equal(small.vertices, coloured_sphere.vertices)
    assert np.array_equal(small.faces, coloured_sphere.faces)
    assert np.array_equal(small.visual.vertex_colors, coloured_sphere.visual.vertex_colors)


def test_density_grid_sends_bounded_chunks():
    sizes = []

    def density(points):
        sizes.append(len(points))
        assert points.shape[1] == 3 and points.dtype == torch.float32
        return points[:, 0]

    grid = density_grid(density, [0.0, 0.0, 0.0], [1.0, 2.0, 3.0], resolution=5, chunk=32)
    assert max(sizes) <= 32 and sum(sizes) == 125
    # Indexed [x, y, z], corners included.
    assert grid.shape == (5, 5, 5)
    assert np.allclose(grid[:, 2, 3], np.linspace(0.0, 1.0, 5))


def test_vertex_colours_follow_color_fn(coloured_sphere):
    colours = coloured_sphere.visual.vertex_colors
    assert colours.dtype == np.uint8 and colours.shape == (len(coloured_sphere.vertices), 4)
    expected = np.round(255.0 * (coloured_sphere.vertices + 0.5))
    assert np.abs(colours[:, :3].astype(float) - expected).max() <= 1.0
    assert np.all(colours[:, 3] == 255)


@pytest.mark.parametrize("value", [0.0, 1000.0])
def test_no_crossing_gives_an_empty_mesh(value):
    mesh = extract_mesh(lambda p: torch.full((len(p),), value), BOX_MIN, BOX_MAX, resolution=16,
                        color_fn=position_color)
    assert mesh.is_empty


def test_small_components_can_be_dropped():
    centre = torch.tensor([0.3, 0.3, 0.3])

    def two_spheres(p):
        return 100.0 * ((p.norm(dim=-1) < 0.2) | ((p - centre).norm(dim=-1) < 0.06)).float()

    kept = extract_mesh(two_spheres, BOX_MIN, BOX_MAX, resolution=RES)
    assert len(kept.split(only_watertight=False)) == 2
    cleaned = extract_mesh(two_spheres, BOX_MIN, BOX_MAX, resolution=RES, min_component_fraction=0.2)
    assert len(cleaned.split(only_watertight=False)) == 1
    assert np.linalg.norm(cleaned.vertices, axis=1).max() < 0.2 + CELL


def test_bad_density_fn_and_arguments_raise():
    with pytest.raises(ValueError, match="returned 1 values"):
        extract_mesh(lambda p: torch.zeros(1), BOX_MIN, BOX_MAX, resolution=8)
    with pytest.raises(ValueError, match="NaN"):
        extract_mesh(lambda p: torch.full((len(p),), float("nan")), BOX_MIN, BOX_MAX, resolution=8)
    with pytest.raises(ValueError, match="box_max"):
        extract_mesh(step_sphere, BOX_MAX, BOX_MIN, resolution=8)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        extract_mesh(step_sphere, BOX_MIN, BOX_MAX, resolution=16, color_fn=lambda p: p[:, :2])


@pytest.mark.parametrize("fmt", SUPPORTED_FORMATS)
def test_export_round_trip(coloured_sphere, tmp_path, fmt):
    path = export_mesh(coloured_sphere, tmp_path / f"sphere.{fmt}")
    loaded = trimesh.load(path, force="mesh")
    assert len(loaded.vertices) == len(coloured_sphere.vertices)
    assert len(loaded.faces) == len(coloured_sphere.faces)
    # GLB is Y-up as glTF requires: (x, y, z) in the Z-up world is (x, z, -y) in the file
    expected = coloured_sphere.vertices[:, [0, 2, 1]] * [1, 1, -1] if fmt == "glb" else coloured_sphere.vertices
    assert np.allclose(loaded.vertices, expected, atol=1e-6)
    if fmt in ("glb", "ply"):
        assert np.array_equal(loaded.visual.vertex_colors, coloured_sphere.visual.vertex_colors)


def test_mesh_bytes_and_format_argument(coloured_sphere, tmp_path):
    data = mesh_bytes(coloured_sphere, "PLY")
    assert isinstance(data, bytes) and data.startswith(b"ply")
    assert mesh_bytes(coloured_sphere, "glb")[:4] == b"glTF"
    path = export_mesh(coloured_sphere, tmp_path / "sphere.bin", format="glb")
    assert path.read_bytes()[:4] == b"glTF"
    with pytest.raises(ValueError, match="glb, ply, obj"):
        mesh_bytes(coloured_sphere, "stl")
    with pytest.raises(ValueError, match="glb, ply, obj"):
        export_mesh(coloured_sphere, tmp_path / "sphere")


@pytest.mark.parametrize("fmt", ["glb", "ply"])
def test_empty_mesh_encodes(fmt):
    loaded = trimesh.load(io.BytesIO(mesh_bytes(trimesh.Trimesh(), fmt)), file_type=fmt, force="mesh")
    assert loaded.is_empty


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_extract_mesh_on_cuda():
    devices = set()

    def density(points):
        devices.add(points.device.type)
        return smooth_sphere(points)

    mesh = extract_mesh(density, BOX_MIN.cuda(), BOX_MAX.cuda(), resolution=32, color_fn=position_color)
    assert devices == {"cuda"}
    assert np.all(np.abs(np.linalg.norm(mesh.vertices, axis=1) - RADIUS) < 0.1 / 31)


def test_glb_is_y_up_and_other_formats_keep_the_world():
    """A chair standing along the world's +Z stands along +Y in GLB viewers."""
    tall = trimesh.creation.box(extents=[0.2, 0.3, 0.9])
    tall.apply_translation([0.0, 0.0, 0.45])  # standing on the ground plane z = 0
    glb = trimesh.load(io.BytesIO(mesh_bytes(tall, "glb")), file_type="glb", force="mesh")
    assert np.allclose(glb.extents, [0.2, 0.9, 0.3]) and np.isclose(glb.bounds[0, 1], 0.0)
    ply = trimesh.load(io.BytesIO(mesh_bytes(tall, "ply")), file_type="ply", force="mesh")
    assert np.allclose(ply.bounds, tall.bounds)
    assert np.allclose(tall.bounds[:, 2], [0.0, 0.9])  # the caller's mesh is left as it was
