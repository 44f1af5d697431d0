"""Per-object fits end to end on a tiny procedural chair: training, evaluation, checkpoints, CLI."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from conftest import TINY_ENCODING
from model.cli.main import main
from model.data.dataset import load_index, load_views
from model.eval.field import evaluate_field
from model.nerf import config
from model.nerf.fields.hashgrid import FieldConfig
from model.nerf.occupancy import OccupancyConfig
from model.nerf.renderer import DENSE, RenderConfig
from model.optimize.fit import FitConfig, fit_object, load_fit, save_fit

SMALL_FIELD = FieldConfig(encoding=TINY_ENCODING, hidden=32, geo_features=15, color_hidden=32)


@pytest.fixture(scope="module")
def chairs(tmp_path_factory):
    root = tmp_path_factory.mktemp("chairs")
    assert main(["data", "synth", "--out", str(root), "--objects", "2", "--views", "24", "--res", "32", "--seed", "3"]) == 0
    return root


@pytest.fixture(scope="module")
def fitted(chairs):
    obj = load_index(chairs)[0].id
    cfg = FitConfig(field=SMALL_FIELD, steps=150, rays_per_step=1024, occupancy=OccupancyConfig(resolution=32), seed=0)
    result = fit_object(load_views(chairs / obj, "train"), cfg, progress=False)
    return obj, cfg, result


def test_fit_learns_the_object(chairs, fitted):
    obj, cfg, result = fitted
    assert result.history[-1]["train_psnr"] > result.history[0]["train_psnr"] + 5
    metrics, renders, mesh = evaluate_field(result.params, cfg.field, result.grid, load_views(chairs / obj, "test"), RenderConfig(), mesh_resolution=48)
    # a blank render scores the floors exactly: the fit must beat them clearly, on the object too
    assert metrics["psnr"] > metrics["floor_psnr"] + 6, metrics
    assert metrics["psnr_fg"] > metrics["floor_psnr_fg"] + 8, metrics
    assert 0.5 < metrics["ssim"] <= 1.0
    assert renders.shape[1:] == (32, 32, 3)
    assert not mesh.is_empty and metrics["chamfer"] < 0.1
    # the hull keeps empty space out of training: few samples per ray compared with the 128 of a dense march
    assert result.history[-1]["samples_per_ray"] < 40
    assert 0 < result.grid.fraction < 0.5


def test_fast_renderer_matches_dense_renderer(chairs, fitted):
    obj, cfg, result = fitted
    test = load_views(chairs / obj, "test")
    fast, _ = evaluate_field(result.params, cfg.field, result.grid, test, RenderConfig(), mesh_resolution=16)[:2]
    dense, _ = evaluate_field(result.params, cfg.field, result.grid, test, DENSE, mesh_resolution=16)[:2]
    assert fast["psnr"] > dense["psnr"] - 0.5


def test_checkpoint_round_trip(tmp_path, fitted):
    obj, cfg, result = fitted
    save_fit(tmp_path / "run", result, cfg, {"object": obj})
    params, grid, scene, cfg2, meta = load_fit(tmp_path / "run")
    assert meta["object"] == obj and cfg2 == cfg and scene == result.scene
    assert config.to_dict(cfg2) == config.to_dict(cfg)
    assert all(torch.equal(params[k], result.params[k]) for k in result.params)
    assert torch.equal(grid.occupied, result.grid.occupied)


def test_fit_rejects_nan_poses(chairs):
    obj = load_index(chairs)[0].id
    views = load_views(chairs / obj, "train")
    views.c2w[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        fit_object(views, FitConfig(field=SMALL_FIELD, steps=1), progress=False)


def test_cli_fit_and_render_bench(chairs, tmp_path):
    obj = load_index(chairs)[1].id
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "model.cli", "fit", "--data", str(chairs), "--object", obj, "--out", str(run),
           "--steps", "30", "--rays", "512", "--grid-resolution", "32", "--mesh-resolution", "32"]
    subprocess.run(cmd, check=True, capture_output=True)
    metrics = json.loads((run / "metrics.json").read_text())
    for key in ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg", "ssim", "wall_s"):
        assert isinstance(metrics[key], float), key
    assert metrics["chamfer"] is None or metrics["chamfer"] >= 0  # 30 steps may not yet form a surface
    assert (run / "mesh.glb").stat().st_size > 0 and any((run / "renders").glob("*.png"))
    out = tmp_path / "bench.json"
    bench = [sys.executable, "-m", "model.cli", "bench", "render", "--fit", str(run), "--json", str(out), "--repeats", "1", "--views", "1"]
    subprocess.run(bench, check=True, capture_output=True)
    report = json.loads(out.read_text())
    modes = {r["mode"]: r for r in report["runs"]}
    assert {"dense", "dense-tight", "occupancy", "fast"} <= set(modes)
    assert all(r["ms"] > 0 and r["psnr"] > 0 and r["samples_per_ray"] >= 0 for r in report["runs"])
    # the tight box changes where samples fall, not how many are evaluated per hitting ray
    assert modes["occupancy"]["samples_per_ray"] < modes["dense-tight"]["samples_per_ray"]


def test_cli_reports_a_missing_object(chairs, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "model.cli", "fit", "--data", str(chairs), "--object", "nope", "--out", str(tmp_path / "r")],
        capture_output=True, text=True,
    )
    assert proc.returncode == 2 and "nope" in proc.stderr


def _quality(result, cfg, test):
    metrics, _, _ = evaluate_field(result.params, cfg.field, result.grid, test, RenderConfig(), mesh_resolution=16)
    return metrics


def test_fit_without_masks_grows_its_grid_from_density(chairs, fitted):
    obj, cfg, with_masks = fitted
    train, test = load_views(chairs / obj, "train"), load_views(chairs / obj, "test")
    result = fit_object(train, replace(cfg, use_masks=False), progress=False)
    assert with_masks.used_masks and not result.used_masks
    # the grid started as every cell the views see and shrank towards the object from the field's own density
    seen = result.history[0]["occupied"]
    assert seen > 0.9 and 0 < result.grid.fraction < 0.75 * seen, (seen, result.grid.fraction)
    metrics = _quality(result, cfg, test)
    assert metrics["psnr"] > metrics["floor_psnr"] + 6 and metrics["psnr_fg"] > metrics["floor_psnr_fg"] + 8, metrics


def test_fit_accepts_images_without_alpha(chairs, fitted):
    obj, cfg, _ = fitted
    train, test = load_views(chairs / obj, "train"), load_views(chairs / obj, "test")
    alpha = train.images[..., 3:]
    opaque = torch.cat([train.images[..., :3] * alpha + (1 - alpha), torch.ones_like(alpha)], dim=-1)  # photos on white
    result = fit_object(replace(train, images=opaque), cfg, progress=False)
    assert not result.used_masks
    metrics = _quality(result, cfg, test)  # scored against the held-out views' own alpha
    assert metrics["psnr"] > metrics["floor_psnr"] + 6 and metrics["psnr_fg"] > metrics["floor_psnr_fg"] + 8, metrics


def _scaled_copy(source: Path, target: Path, scale: float) -> None:
    """The object folder with its scene box, camera positions and mesh scaled by ``scale``."""
    import trimesh

    shutil.copytree(source, target)
    transforms = json.loads((target / "transforms.json").read_text())
    transforms["aabb"] = [[v * scale for v in corner] for corner in transforms["aabb"]]
    for frame in transforms["frames"]:
        for row in frame["transform_matrix"][:3]:
            row[3] *= scale
    (target / "transforms.json").write_text(json.dumps(transforms))
    mesh = trimesh.load(target / "mesh.ply", force="mesh")
    mesh.apply_scale(scale)
    mesh.export(target / "mesh.ply")


def test_fit_is_invariant_to_the_scene_scale(chairs, tmp_path):
    obj = load_index(chairs)[0].id
    _scaled_copy(chairs / obj, tmp_path / "x3", 3.0)
    cfg = FitConfig(field=SMALL_FIELD, steps=120, rays_per_step=1024, occupancy=OccupancyConfig(resolution=32), seed=0)
    scores = []
    for folder in (chairs / obj, tmp_path / "x3"):
        result = fit_object(load_views(folder, "train"), cfg, progress=False)
        metrics, _, _ = evaluate_field(result.params, cfg.field, result.grid, load_views(folder, "test"), RenderConfig(), mesh_resolution=32)
        scores.append(metrics)
    assert scores[1]["psnr"] == pytest.approx(scores[0]["psnr"], abs=0.5)
    assert scores[1]["psnr_fg"] == pytest.approx(scores[0]["psnr_fg"], abs=0.5)
    assert scores[0]["psnr"] > scores[0]["floor_psnr"] + 6
    # Chamfer distances are reported in scene-box units, so they agree too
    assert scores[1]["chamfer"] == pytest.approx(scores[0]["chamfer"], rel=0.2, abs=2e-3)
