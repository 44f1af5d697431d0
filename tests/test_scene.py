"""Scene boxes, pinhole intrinsics and importing scenes in the NeRF-synthetic and nerfstudio layouts."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from model.cli.main import main
from model.data.dataset import DatasetError, load_index, load_views
from model.data.transforms import camera_box, downscale_rgba, import_transforms
from model.eval.metrics import image_quality
from model.nerf.occupancy import MaintainedGrid, OccupancyConfig
from model.nerf.rays import Intrinsics, camera_directions, pixel_rays, project
from model.nerf.scene import UNIT_BOX, SceneBox


def test_scene_box_maps_to_the_unit_cube_and_back():
    box = SceneBox((-1.5, -1.0, 0.0), (1.5, 2.0, 1.0))
    points = torch.tensor([[-1.5, -1.0, 0.0], [1.5, 2.0, 1.0], [0.0, 0.5, 0.5], [9.0, 9.0, 9.0]])
    unit = box.to_unit(points)
    assert torch.allclose(unit[:3], torch.tensor([[0.0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5]]))
    assert torch.equal(unit[3], torch.ones(3))  # clamped onto the box
    assert torch.allclose(box.from_unit(unit[:3]), points[:3])
    # one world unit along x covers 1/3 of the unit cube; along z all of it
    lengths = box.unit_lengths(torch.tensor([[1.0, 0, 0], [0, 0, 1.0]]))
    assert torch.allclose(lengths, torch.tensor([1 / 3, 1.0]))
    with pytest.raises(ValueError, match="min < max"):
        SceneBox((0, 0, 0), (1, 0, 1))
    with pytest.raises(ValueError, match="finite"):
        SceneBox((0, 0, float("nan")), (1, 1, 1))


def test_intrinsics_with_unequal_focals_and_an_off_centre_principal_point():
    camera = Intrinsics(width=40, height=30, fx=50.0, fy=35.0, cx=13.0, cy=21.0)
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.2, -0.1, 3.0])
    origins, directions = pixel_rays(c2w, camera)
    assert origins.shape == directions.shape == (30, 40, 3)
    # a point along the ray of pixel (row 5, col 31) projects back to that pixel's centre
    point = origins[5, 31] + 2.5 * directions[5, 31]
    x, y, depth = project((point - c2w[:3, 3])[None] @ c2w[:3, :3], camera)
    assert float(x) == pytest.approx(31.5, abs=1e-4) and float(y) == pytest.approx(5.5, abs=1e-4) and float(depth) > 0
    # the principal point's ray is the optical axis
    axis = camera_directions(Intrinsics(4, 4, 10.0, 20.0, 2.5, 1.5))[1, 2]
    assert torch.allclose(axis, torch.tensor([0.0, 0.0, -1.0]))
    with pytest.raises(ValueError, match="positive"):
        Intrinsics(4, 4, 0.0, 1.0, 2.0, 2.0)


def test_maintained_grid_is_seeded_and_deterministic():
    def blob(points):
        return 100.0 * (points.norm(dim=-1) < 0.2).float()

    grids = []
    for _ in range(2):
        grid = MaintainedGrid(UNIT_BOX, OccupancyConfig(resolution=16, warmup_steps=2, update_every=2, seed=3))
        assert grid.grid.fraction == 1.0 and not grid.step(0, blob) and grid.step(2, blob)
        grids.append(grid.grid.occupied)
    assert torch.equal(grids[0], grids[1]) and 0 < grids[0].float().mean() < 0.2


def test_a_blank_render_scores_exactly_the_floor():
    target = torch.ones(2, 8, 8, 4)
    target[:, 2:6, 2:6, :3] = torch.tensor([0.8, 0.1, 0.1])
    target[:, :2, :, 3] = 0.0
    blank = torch.ones(2, 8, 8, 3)
    scores = image_quality(blank, target, torch.zeros(2, 8, 8))
    assert scores["psnr"] == pytest.approx(scores["floor_psnr"]) and scores["psnr_fg"] == pytest.approx(scores["floor_psnr_fg"])
    perfect = target[..., :3] * target[..., 3:] + (1 - target[..., 3:])
    good = image_quality(perfect, target, target[..., 3])
    assert good["psnr_fg"] > scores["floor_psnr_fg"] + 50


# ---------------------------------------------------------------------------------------------
# Importing scenes


def _look_at(position: np.ndarray) -> np.ndarray:
    forward = -position / np.linalg.norm(position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up, -forward, position
    return pose


def _write_images(folder, names, size=(16, 12), alpha=True):
    for n, name in enumerate(names):
        rgba = np.zeros((size[1], size[0], 4), dtype=np.uint8)
        rgba[..., 0] = 25 * n
        rgba[..., 3] = 255
        if alpha:
            rgba[:3, :, 3] = 0
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rgba if alpha else rgba[..., :3]).save(path)


def _poses(count, radius=4.0):
    angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
    return [_look_at(np.array([radius * math.cos(a), radius * math.sin(a), 1.0])) for a in angles]


def test_import_nerf_synthetic_layout(tmp_path):
    src = tmp_path / "lego"
    for split, count in (("train", 4), ("val", 1), ("test", 2)):
        names = [f"{split}/r_{i}" for i in range(count)]
        _write_images(src, [n + ".png" for n in names])
        frames = [{"file_path": "./" + n, "transform_matrix": p.tolist()} for n, p in zip(names, _poses(count))]
        (src / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    report = import_transforms(src, tmp_path / "out")
    assert report["layout"] == "nerf-synthetic" and report["splits"] == {"train": 4, "val": 1, "test": 2}
    assert "convention" in report["aabb_source"]
    train = load_views(tmp_path / "out" / "lego", "train")
    assert train.scene == SceneBox.cube(1.5) and train.has_alpha and len(train.files) == 4
    assert train.camera.fx == pytest.approx(0.5 * 16 / math.tan(0.345))
    assert len(load_views(tmp_path / "out" / "lego", "test").files) == 2
    assert load_index(tmp_path / "out").ids() == ["lego"]


def test_import_nerfstudio_layout_keeps_per_frame_intrinsics_and_downscales(tmp_path):
    src = tmp_path / "capture"
    names = [f"images/frame_{i:05d}.jpg" for i in range(9)]
    _write_images(src, names, size=(16, 12), alpha=False)
    frames = [{"file_path": n, "transform_matrix": p.tolist()} for n, p in zip(names, _poses(9))]
    frames[3].update({"fl_x": 30.0, "fl_y": 24.0, "cx": 7.0, "cy": 5.0})
    (src / "transforms.json").write_text(json.dumps({"fl_x": 20.0, "fl_y": 22.0, "cx": 9.0, "cy": 6.5, "w": 16, "h": 12,
                                                    "camera_model": "OPENCV", "k1": 0.0, "frames": frames}))
    report = import_transforms(src, tmp_path / "out", downscale=2, test_every=4)
    assert report["layout"] == "nerfstudio" and report["splits"] == {"train": 6, "test": 3}
    assert report["aabb_source"] == "derived from the cameras" and (report["width"], report["height"]) == (8, 6)
    views = load_views(tmp_path / "out" / "capture", None)
    assert not views.has_alpha
    assert views.cameras[0] == Intrinsics(8, 6, 10.0, 11.0, 4.5, 3.25)
    assert views.cameras[3] == Intrinsics(8, 6, 15.0, 12.0, 3.5, 2.5)
    box = views.scene
    assert max(abs(c) for c in (np.array(box.min) + np.array(box.max)) / 2) < 0.3  # centred on what the cameras look at


def test_import_rejects_distortion_and_unknown_layouts(tmp_path):
    src = tmp_path / "distorted"
    _write_images(src, ["a.png"])
    (src / "transforms.json").write_text(json.dumps({"fl_x": 20.0, "k1": 0.1, "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(DatasetError, match="distortion k1=0.1 is not supported"):
        import_transforms(src, tmp_path / "out")
    (src / "transforms.json").write_text(json.dumps({"fl_x": 20.0, "camera_model": "EQUIRECTANGULAR", "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(DatasetError, match="camera_model"):
        import_transforms(src, tmp_path / "out")
    with pytest.raises(DatasetError, match="neither"):
        import_transforms(tmp_path, tmp_path / "out")
    assert main(["data", "import-transforms", str(src), "--out", str(tmp_path / "out")]) == 1


def test_downscale_averages_premultiplied_colour():
    image = np.zeros((2, 2, 4), dtype=np.uint8)
    image[0, 0] = (255, 0, 0, 255)
    image[1, 1] = (0, 255, 0, 0)  # transparent green must not tint the result
    out = downscale_rgba(image, 2)
    assert out.shape == (1, 1, 4) and tuple(out[0, 0]) == (255, 0, 0, 64)


def test_camera_box_centres_on_the_looked_at_point():
    poses = np.stack([p @ np.diag([1, 1, 1, 1.0]) for p in _poses(8)])
    poses[:, :3, 3] += np.array([1.0, 2.0, 0.0])
    box = camera_box(poses, [Intrinsics.centred(16, 16, 16.0)] * 8)
    centre = (np.array(box.min) + np.array(box.max)) / 2
    assert np.allclose(centre[:2], [1.0, 2.0], atol=1e-6)
