"""Per-object fits end to end on a tiny procedural chair: training, evaluation, checkpoints, CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from conftest import TINY_ENCODING
from model.cli import main
from model.data.dataset import load_index, load_views
from model.evaluate import evaluate_field
from model.field import FieldConfig
from model.fit import FitConfig, fit_object, load_fit, save_fit
from model.renderer import DENSE, RenderConfig

SMALL_FIELD = FieldConfig(encoding=TINY_ENCODING, hidden=32, geo_features=15, color_hidden=32)


@pytest.fixture(scope="module")
def chairs(tmp_path_factory):
    root = tmp_path_factory.mktemp("chairs")
    assert main(["data", "synth", "--out", str(root), "--objects", "2", "--views", "24", "--res", "32", "--seed", "3"]) == 0
    return root


@pytest.fixture(scope="module")
def fitted(chairs):
    obj = load_index(chairs)[0].id
    cfg = FitConfig(field=SMALL_FIELD, steps=150, rays_per_step=1024, grid_resolution=32, seed=0)
    result = fit_object(load_views(chairs / obj, "train"), cfg, progress=False)
    return obj, cfg, result


def test_fit_learns_the_object(chairs, fitted):
    obj, cfg, result = fitted
    assert result.history[-1]["train_psnr"] > result.history[0]["train_psnr"] + 5
    metrics, renders, mesh = evaluate_field(result.params, cfg.field, result.grid, load_views(chairs / obj, "test"), RenderConfig(), mesh_resolution=48)
    assert metrics["psnr"] > 20.0, metrics
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
    params, grid, cfg2, meta = load_fit(tmp_path / "run")
    assert meta["object"] == obj and cfg2.to_dict() == cfg.to_dict()
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
    for key in ("psnr", "ssim", "wall_s"):
        assert isinstance(metrics[key], float), key
    assert metrics["chamfer"] is None or metrics["chamfer"] >= 0  # 30 steps may not yet form a surface
    assert (run / "mesh.glb").stat().st_size > 0 and any((run / "renders").glob("*.png"))
    out = tmp_path / "bench.json"
    bench = [sys.executable, "-m", "model.cli", "bench", "render", "--fit", str(run), "--json", str(out), "--repeats", "1", "--views", "1"]
    subprocess.run(bench, check=True, capture_output=True)
    report = json.loads(out.read_text())
    modes = {r["mode"]: r for r in report["runs"]}
    assert "dense" in modes and "fast" in modes
    assert all(r["ms"] > 0 and r["psnr"] > 0 for r in report["runs"])


def test_cli_reports_a_missing_object(chairs, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "model.cli", "fit", "--data", str(chairs), "--object", "nope", "--out", str(tmp_path / "r")],
        capture_output=True, text=True,
    )
    assert proc.returncode == 2 and "nope" in proc.stderr
