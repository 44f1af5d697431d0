"""Training the prior end to end on tiny procedural chairs: learning, export, resume, torchrun,
evaluation commands."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from model.cli.main import main
from model.data.category import free_space_grids, free_space_points, load_category, shape_grids
from model.eval.prior import compression, disentanglement, spread_instances
from model.nerf import config
from model.nerf.scene import UNIT_BOX
from model.prior.codes import generate, swap_codes
from model.prior.hypernet import HyperNetConfig, HyperNetwork, preset
from model.prior.io import PRIOR_META, PRIOR_WEIGHTS, load_prior
from model.train.prior import CHECKPOINT, Workers, step_instances, train
from conftest import tiny_train

ROOT = Path(__file__).resolve().parents[1]


def test_category_loads_the_train_split_as_uint8(chairs):
    data = load_category(chairs, progress=False)
    assert data.images.dtype == torch.uint8 and data.images.shape[1:] == (24, 32, 32, 4)
    assert 1 <= data.shapes and len(data.instances) == 2 * data.shapes  # two colour variants per mesh
    assert data.shape_index[0] == data.shape_index[1] != data.shape_index[2]
    grids = shape_grids(data, 24, progress=False)
    # procedural chairs fill about half the box, and the hull grows by one cell: it still carves a quarter away
    assert grids.shape == (data.shapes, 24, 24, 24) and 0.2 < grids.float().mean() < 0.75


def test_mesh_occupancy_is_inside_the_hull_and_box_is_everything(chairs):
    data = load_category(chairs, progress=False)
    hull = shape_grids(data, 24, progress=False, source="hull")
    mesh = shape_grids(data, 24, progress=False, source="mesh")
    box = shape_grids(data, 24, progress=False, source="box")
    assert box.all() and mesh.shape == hull.shape == box.shape
    # the surface band is tighter than the hull, and (up to the hull's own one-cell margin) inside it
    assert 0 < mesh.float().mean() < hull.float().mean()
    assert (mesh & ~free_space_grids(hull)).sum() == 0
    with pytest.raises(ValueError, match="occupancy source"):
        shape_grids(data, 24, progress=False, source="voxels")


def test_free_space_points_avoid_the_grown_object():
    occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
    occupied[3:5, 3:5, 3:5] = True
    points = free_space_points(free_space_grids(occupied[None])[0], UNIT_BOX, 4096, torch.Generator().manual_seed(0))
    assert 0 < points.shape[0] < 4096
    cells = ((points + 0.5) * 8).floor().long()
    assert not ((cells >= 2) & (cells <= 5)).all(dim=1).any()  # the cube plus a one-cell margin


def test_workers_draw_distinct_instances():
    first = step_instances(10, 2, seed=0, step=3, workers=Workers(0, 2))
    second = step_instances(10, 2, seed=0, step=3, workers=Workers(1, 2))
    assert len(first) == len(second) == 2 and not set(first) & set(second)
    assert step_instances(10, 2, 0, 3, Workers(0, 2)) == first
    assert step_instances(10, 2, 0, 4, Workers(0, 2)) != first or step_instances(10, 2, 0, 5, Workers(0, 2)) != first


def test_training_learns_and_exports_the_prior(trained):
    run, summary = trained
    history = json.loads((run / "history.json").read_text())
    assert history[-1]["train_psnr"] > history[0]["train_psnr"] + 3
    last = history[-1]
    # a blank render scores exactly the floor: the prior must beat it clearly, on the object too
    assert last["val_psnr"] > last["val_floor_psnr"] + 3
    assert last["val_psnr_fg"] > last["val_floor_psnr_fg"] + 3
    assert history[-1]["rays_per_s"] > 0 and history[-1]["samples_per_ray"] > 0
    assert (run / PRIOR_WEIGHTS).is_file() and (run / CHECKPOINT).is_file()
    meta = json.loads((run / PRIOR_META).read_text())
    assert len(meta["instances"]) == summary["instances"] and meta["weights_dtype"] == "float16"
    assert summary["parameters"]["tables"] > 0


def test_exported_prior_reproduces_the_trained_nerfs(trained):
    run, _ = trained
    prior = load_prior(run)
    net, meta = prior.net, prior.meta
    assert prior.scene == UNIT_BOX
    state = torch.load(run / CHECKPOINT, weights_only=False)["model"]
    index = torch.tensor([0])
    full = HyperNetwork(config.from_dict(HyperNetConfig, meta["hypernet"]), len(meta["instances"]), [i["shape_index"] for i in meta["instances"]])
    full.load_state_dict(state)
    with torch.no_grad():
        a, b = net(index), full(index)
    for name in a:
        assert torch.allclose(a[name], b[name], rtol=2e-2, atol=2e-3), name


def test_resume_continues_exactly(chairs, tmp_path):
    straight = tmp_path / "straight"
    train(chairs, straight, preset("tiny"), tiny_train(12), progress=False)
    split = tmp_path / "split"
    train(chairs, split, preset("tiny"), tiny_train(12), until=5, progress=False)
    assert not (split / PRIOR_WEIGHTS).exists() and torch.load(split / CHECKPOINT, weights_only=False)["step"] == 5
    train(chairs, split, preset("tiny"), tiny_train(1), resume=True, progress=False)  # the checkpoint's settings win
    a = torch.load(straight / CHECKPOINT, weights_only=False)["model"]
    b = torch.load(split / CHECKPOINT, weights_only=False)["model"]
    for name in a:
        assert torch.allclose(a[name], b[name], atol=1e-6), name


def test_code_noise_trains_a_different_prior_and_is_recorded(chairs, tmp_path):
    plain = train(chairs, tmp_path / "plain", preset("tiny"), tiny_train(6), progress=False)
    noisy_cfg = tiny_train(6)
    noisy_cfg.code_noise = 0.5
    noisy = train(chairs, tmp_path / "noisy", preset("tiny"), noisy_cfg, progress=False)
    assert json.loads((tmp_path / "noisy" / PRIOR_META).read_text())["train"]["code_noise"] == 0.5
    a = torch.load(tmp_path / "plain" / CHECKPOINT, weights_only=False)["model"]
    b = torch.load(tmp_path / "noisy" / CHECKPOINT, weights_only=False)["model"]
    assert any(not torch.allclose(a[k], b[k]) for k in a)
    assert plain["steps"] == noisy["steps"] == 6
    assert main(["train", "--data", str(chairs), "--out", str(tmp_path / "r"), "--preset", "tiny", "--steps", "2", "--code-noise", "-1"]) == 2


def test_resume_without_checkpoint_says_what_to_do(chairs, tmp_path):
    with pytest.raises(FileNotFoundError, match="without --resume"):
        train(chairs, tmp_path, preset("tiny"), tiny_train(2), resume=True, progress=False)


def test_torchrun_trains_data_parallel_with_gloo(chairs, tmp_path):
    run = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m", "model.cli", "train",
        "--data", str(chairs), "--out", str(run), "--preset", "tiny", "--steps", "4", "--objects-per-step", "2",
        "--rays", "256", "--validate-every", "0",
    ]
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    meta = json.loads((run / PRIOR_META).read_text())
    assert meta["summary"]["workers"] == 2 and meta["summary"]["steps"] == 4


def test_cli_train_rejects_bad_settings(chairs, tmp_path):
    with pytest.raises(SystemExit) as refused:  # argparse: an unknown preset is a usage error
        main(["train", "--data", str(chairs), "--out", str(tmp_path / "r"), "--preset", "huge", "--steps", "2"])
    assert refused.value.code == 2
    assert main(["train", "--data", str(chairs), "--out", str(tmp_path / "r"), "--preset", "tiny", "--steps", "0"]) == 2


def test_compression_report_compares_with_per_object_fits(trained, chairs, tmp_path):
    run, _ = trained
    report = compression(run, chairs, objects=2, fits=tmp_path / "fits", fit_steps=40, mesh_resolution=24)
    assert report["objects"] == 2
    for side in ("hypernet", "per_object"):
        scores = report[side]
        # blank renders score the floors exactly; both sides must be clearly above them
        assert scores["psnr"] > scores["floor_psnr"] + 3 and scores["psnr_fg"] > scores["floor_psnr_fg"] + 3
        assert 0 < scores["ssim"] <= 1
    assert report["psnr_gap_db"] == pytest.approx(report["per_object"]["psnr"] - report["hypernet"]["psnr"])
    storage = report["storage"]
    # counted at the prior's half precision, with fits sharing geometry per mesh as the prior does
    field = preset("tiny").field
    geometry = sum(math.prod(field.param_shapes()[n]) for n in field.shape_param_names())
    colour = sum(math.prod(field.param_shapes()[n]) for n in field.color_param_names())
    assert storage["weights_dtype"] == "float16"
    assert storage["fits_shared_bytes"] == pytest.approx(2 * (storage["shapes"] * geometry + storage["instances"] * colour))
    assert storage["fits_unshared_bytes"] == 2 * storage["instances"] * (geometry + colour)
    # the counted prior is the exported file's tensors, give or take the file's header
    assert 0 <= storage["prior_file_bytes"] - storage["prior_bytes"] < 4096
    curve = storage["curve"]
    assert [r["instances"] for r in curve] == sorted(r["instances"] for r in curve)
    slopes = [(b["prior_bytes"] - a["prior_bytes"], b["fits_shared_bytes"] - a["fits_shared_bytes"]) for a, b in zip(curve, curve[1:])]
    assert all(prior < fits for prior, fits in slopes)  # the prior grows more slowly than the fits
    # the fits are cached: a second evaluation reuses them
    written = {p: p.stat().st_mtime_ns for p in (tmp_path / "fits").glob("*/field.safetensors")}
    again = compression(run, chairs, objects=2, fits=tmp_path / "fits", fit_steps=40, mesh_resolution=24)
    assert again["per_object"] == report["per_object"]
    assert {p: p.stat().st_mtime_ns for p in written} == written and len(written) == 2
    with pytest.raises(ValueError, match="no-mrhe"):
        compression(run, chairs, objects=1, ablation="no-mrhe")


def test_spread_instances_prefers_distinct_shapes():
    meta = {"instances": [{"id": str(i), "shape_index": i // 3} for i in range(12)]}
    picks = spread_instances(meta, 4)
    assert len({meta["instances"][p]["shape_index"] for p in picks}) == 4
    assert len(spread_instances(meta, 20)) == 12


def test_swap_command_writes_renders_mesh_and_figures(trained, chairs, tmp_path):
    run, _ = trained
    meta = json.loads((run / PRIOR_META).read_text())
    a, b = meta["instances"][0]["id"], meta["instances"][-1]["id"]
    out = tmp_path / "swap"
    code = main(["swap", "--run", str(run), "--data", str(chairs), "--shape", a, "--color", b, "--out", str(out), "--mesh-resolution", "24"])
    assert code == 0
    figures = json.loads((out / "swap.json").read_text())
    assert figures["shape"] == a and figures["color"] == b
    assert len(list(out.glob("view_*.png"))) == 12 and (out / "mesh.glb").is_file()
    assert main(["swap", "--run", str(run), "--data", str(chairs), "--shape", "nope", "--color", b, "--out", str(out)]) == 2


def test_disentanglement_report(trained, chairs, tmp_path):
    run, _ = trained
    grid = tmp_path / "grid.png"
    report = disentanglement(run, chairs, pairs=2, min_colour_distance=0.0, grid_png=grid)
    assert report["pairs"] >= 1 and 0 <= report["pass_fraction"] <= 1
    row = report["rows"][0]
    assert row["shape"] != row["color"] and row["colour_error_to_color_source"] >= 0
    assert report["geometry_max_density_difference"] == 0.0 and "by construction" in report["geometry"]
    assert grid.is_file()


def test_swapped_geometry_is_the_shape_sources_by_construction(trained):
    run, _ = trained
    prior = load_prior(run)
    a, b = 0, len(prior.instances) - 1
    swapped, own = swap_codes(prior.net, a, b), generate(prior.net, a)
    points = torch.rand(1, 2048, 3, generator=torch.Generator().manual_seed(1))
    field = prior.net.cfg.field
    for name in field.shape_param_names():
        assert torch.equal(swapped[name], own[name]), name
    assert torch.equal(field.density(swapped, points)[0], field.density(own, points)[0])
    # the colour does change: the swap carries B's colour net, not A's
    assert any(not torch.equal(swapped[n], own[n]) for n in field.color_param_names())


def test_cached_fits_are_redone_when_the_code_changes(chairs, tmp_path):
    from model.eval.prior import per_object_fit
    from model.optimize.fit import FitConfig

    obj = load_category(chairs, progress=False).instances[0].id
    cfg = FitConfig(field=preset("tiny").field, steps=5, rays_per_step=256)
    first, _ = per_object_fit(chairs, obj, tmp_path, cfg, "cpu", 16)
    weights = tmp_path / obj / "field.safetensors"
    written = weights.stat().st_mtime_ns
    per_object_fit(chairs, obj, tmp_path, cfg, "cpu", 16)
    assert weights.stat().st_mtime_ns == written  # same settings, data and code: reused
    metrics = json.loads((tmp_path / obj / "metrics.json").read_text())
    metrics["code_version"] = "made-by-older-code"
    (tmp_path / obj / "metrics.json").write_text(json.dumps(metrics))
    again, _ = per_object_fit(chairs, obj, tmp_path, cfg, "cpu", 16)
    assert weights.stat().st_mtime_ns != written and again["code_version"] == first["code_version"] != "made-by-older-code"
