"""Test-time optimisation on the tiny prior: it learns, it reports and stops when asked, and every
hard input ends with a clear error or a finite result; the invert command and the generalisation
table run end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from model.cli.main import main
from model.data.cameras import look_at
from model.data.dataset import load_index, load_views
from model.eval.generalization import GeneralizationConfig, frechet_distance, generalization
from model.nerf.rays import Intrinsics
from model.optimize.tto import CodeGaussian, TTOConfig, TTOError, invert
from model.prior.io import load_prior
from model.prior.outputs import load_nerf

FAST = dict(steps=40, rays_per_step=256, init_rays=128, progress_every=5, patience=0)


@pytest.fixture(scope="module")
def prior(trained):
    return load_prior(trained[0])


@pytest.fixture(scope="module")
def unseen(chairs):
    """One view (and the rest) of a test-split object the prior never saw."""
    object_id = next(e.id for e in load_index(chairs) if e.split == "test")
    return load_views(chairs / object_id, "test"), load_views(chairs / object_id, "train")


def _loss_of(result) -> float:
    return result.history[-1]["loss"]


def test_tto_lowers_the_loss_from_its_start_and_stays_finite(prior, unseen):
    held, _ = unseen
    view = held.subset([0])
    result = invert(prior.net, prior.scene, view.images, view.c2w, view.cameras, TTOConfig(**FAST, init="mean"))
    first, last = result.history[0], result.history[-1]
    assert last["loss"] < 0.8 * first["loss"], (first, last)
    assert result.init == "mean" and not result.stopped
    assert all(torch.isfinite(v).all() for v in result.params.values())
    assert result.shape_code.shape == (prior.net.cfg.shape_code_dim,) and result.color_code.shape == (prior.net.cfg.color_code_dim,)
    assert 0 < result.grid.fraction < 1


def test_nearest_start_picks_a_training_instance(prior, unseen):
    held, _ = unseen
    view = held.subset([0])
    result = invert(prior.net, prior.scene, view.images, view.c2w, view.cameras, TTOConfig(**{**FAST, "steps": 2}))
    assert result.init.startswith("nearest:") and 0 <= int(result.init.split(":")[1]) < prior.net.instances


def test_the_two_round_nearest_scan_keeps_the_best_silhouettes_then_the_best_colour(prior, chairs):
    from model.nerf.renderer import RenderConfig
    from model.optimize.pose import PixelBank
    from model.optimize.tto import instance_losses, nearest_instance

    net, field, scene = prior.net, prior.net.cfg.field, prior.scene
    shape_of = net.shape_index
    shapes = int(shape_of.max()) + 1
    assert net.instances > shapes  # colour variants share shapes
    first = [int((shape_of == s).nonzero()[0]) for s in range(shapes)]
    render = RenderConfig(samples_per_ray=32, termination_threshold=0.0)
    calls = []
    original = net.params_from_codes
    net.params_from_codes = lambda *a: calls.append(1) or original(*a)
    try:
        for inst in prior.instances[:3]:
            views = load_views(chairs / inst["id"], "train").subset([0])
            batch = PixelBank(views.images, views.cameras, "cpu").sample(256, views.c2w, torch.Generator().manual_seed(0))
            calls.clear()
            full = nearest_instance(net, field, scene, batch, render, shortlist=0, silhouette=True)
            assert len(calls) == net.instances
            assert full == int(torch.argmin(instance_losses(net, field, scene, batch, render)))
            calls.clear()
            two_round = nearest_instance(net, field, scene, batch, render, shortlist=1, silhouette=True)
            evaluated = len(calls)
            best_shape = int(torch.argmin(instance_losses(net, field, scene, batch, render, first, silhouette=True)))
            variants = (shape_of == best_shape).nonzero()[:, 0].tolist()
            assert evaluated == shapes + len(variants) < net.instances
            assert two_round == variants[int(torch.argmin(instance_losses(net, field, scene, batch, render, variants)))]
            assert nearest_instance(net, field, scene, batch, render, shortlist=shapes, silhouette=True) == full
    finally:
        del net.params_from_codes
    # density comes from the shape code alone, so colour variants have one silhouette score and
    # the first variant stands for its shape without bias; their colour scores differ
    silhouettes = instance_losses(net, field, scene, batch, render, list(range(net.instances)), silhouette=True)
    colours = instance_losses(net, field, scene, batch, render)
    for s in range(shapes):
        same = shape_of == s
        assert torch.allclose(silhouettes[same], silhouettes[same][0].expand(int(same.sum())), atol=1e-6)
    assert not torch.allclose(colours[shape_of == 0], colours[shape_of == 0][0].expand(int((shape_of == 0).sum())))


def test_progress_is_reported_and_should_stop_ends_the_run(prior, unseen):
    held, _ = unseen
    view = held.subset([0])
    seen = []
    result = invert(prior.net, prior.scene, view.images, view.c2w, view.cameras, TTOConfig(**FAST), progress=seen.append,
                    should_stop=lambda: len(seen) >= 3)
    assert result.stopped and len(seen) == 3 and seen[-1]["step"] == 10
    assert {"step", "steps", "phase", "loss", "psnr", "elapsed_s"} <= set(seen[0])


def test_finetune_changes_the_nerf_but_not_the_codes(prior, unseen):
    held, _ = unseen
    view = held.subset([0])
    cfg = TTOConfig(**{**FAST, "steps": 10}, finetune_steps=20)
    codes_only = invert(prior.net, prior.scene, view.images, view.c2w, view.cameras, TTOConfig(**{**FAST, "steps": 10}))
    tuned = invert(prior.net, prior.scene, view.images, view.c2w, view.cameras, cfg)
    assert torch.equal(tuned.shape_code, codes_only.shape_code)
    assert any(not torch.equal(tuned.params[k], codes_only.params[k]) for k in tuned.params)
    assert [h["phase"] for h in tuned.history][-1] == "finetune"
    assert all(torch.isfinite(v).all() for v in tuned.params.values())


def test_the_code_prior_favours_the_codebook_over_codes_as_far_off_it(prior):
    rows = prior.net.shape_codes.weight.detach()
    gaussian = CodeGaussian.fit(rows)
    assert float(gaussian.distance2(gaussian.mean)) == pytest.approx(0.0, abs=1e-9)
    offsets = rows - gaussian.mean
    random = torch.randn(rows.shape, generator=torch.Generator().manual_seed(0))
    elsewhere = gaussian.mean + random / random.norm(dim=1, keepdim=True) * offsets.norm(dim=1, keepdim=True)
    assert float(gaussian.distance2(rows).max()) < 0.5 * float(gaussian.distance2(elsewhere).min())


def test_frechet_distance_is_zero_for_the_same_features_and_grows_with_a_shift():
    features = np.random.default_rng(0).normal(size=(400, 8))
    assert frechet_distance(features, features) == pytest.approx(0.0, abs=1e-6)
    assert frechet_distance(features, features + 1.0) == pytest.approx(8.0, rel=0.05)


# ---------------------------------------------------------------------------------------------
# Hard cases: a clear error or a finite, reported result, never NaN


def _finite(result) -> bool:
    return all(math.isfinite(h["loss"]) for h in result.history) and all(torch.isfinite(v).all() for v in result.params.values())


def test_view_from_straight_above_is_finite(prior):
    camera = Intrinsics.from_fov(24, 24, 2 * math.atan(0.5))
    pose = torch.tensor(look_at(np.array([0.0, 0.0, 2.0]), up=np.array([0.0, 1.0, 0.0])), dtype=torch.float32)[None]
    image = torch.ones(1, 24, 24, 4)
    image[:, 8:16, 8:16, :3] = 0.3
    result = invert(prior.net, prior.scene, image, pose, [camera], TTOConfig(**{**FAST, "steps": 10}))
    assert _finite(result)


def test_non_square_image_of_another_resolution_is_finite(prior, unseen):
    held, _ = unseen
    view = held.subset([0])
    image = torch.nn.functional.interpolate(view.images.permute(0, 3, 1, 2), size=(40, 56), mode="bilinear").permute(0, 2, 3, 1)
    base = view.cameras[0]
    camera = Intrinsics(56, 40, base.fx * 56 / base.width, base.fx * 56 / base.width, 28.0, 20.0)
    result = invert(prior.net, prior.scene, image, view.c2w, [camera], TTOConfig(**{**FAST, "steps": 10}))
    assert _finite(result)


def test_wrong_pose_gives_a_finite_result(prior, unseen):
    held, _ = unseen
    view = held.subset([0])
    turned = torch.tensor(look_at(np.array([-2.0, 0.3, 0.4])), dtype=torch.float32)[None]
    result = invert(prior.net, prior.scene, view.images, turned, view.cameras, TTOConfig(**{**FAST, "steps": 10}))
    assert _finite(result)


@pytest.mark.parametrize("case, message", [
    ("empty", "no object"),
    ("white", "blank white"),
    ("inside", "inside the scene box"),
    ("skewed", "not orthonormal"),
    ("nan", "NaN"),
    ("size", "camera is"),
])
def test_unusable_inputs_are_refused_with_a_clear_message(prior, unseen, case, message):
    held, _ = unseen
    view = held.subset([0])
    images, c2w, cameras = view.images.clone(), view.c2w.clone(), list(view.cameras)
    if case == "empty":
        images[..., 3] = 0.0
    elif case == "white":
        images[:] = 1.0
    elif case == "inside":
        c2w[0, :3, 3] = 0.0
    elif case == "skewed":
        c2w[0, :3, :3] *= 2.0
    elif case == "nan":
        images[0, 0, 0, 0] = float("nan")
    elif case == "size":
        cameras = [Intrinsics.from_fov(10, 10, 0.7)]
    with pytest.raises(TTOError, match=message):
        invert(prior.net, prior.scene, images, c2w, cameras, TTOConfig(**FAST))


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="at least 1"):
        TTOConfig(steps=0)
    with pytest.raises(ValueError, match="init"):
        TTOConfig(init="random")


# ---------------------------------------------------------------------------------------------
# Commands


def test_invert_command_writes_codes_nerf_renders_turntable_and_mesh(trained, unseen, tmp_path):
    held, _ = unseen
    folder = Path(held.mesh_path).parent if held.mesh_path else None
    object_dir = folder or tmp_path
    image = tmp_path / "photo.png"
    Image.fromarray((held.images[0].numpy() * 255).round().astype(np.uint8), "RGBA").save(image)
    transforms = json.loads((object_dir / "transforms.json").read_text())
    frame = next(f for f in transforms["frames"] if f["file_path"].endswith(held.files[0].removesuffix(".png")) or f["file_path"] == held.files[0])
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"camera_angle_x": transforms["camera_angle_x"], "frames": [{"transform_matrix": frame["transform_matrix"]}]}))
    out = tmp_path / "inverted"
    assert main(["invert", "--run", str(trained[0]), "--image", str(image), "--pose", str(pose), "--out", str(out),
                 "--steps", "10", "--rays", "256", "--mesh-resolution", "32"]) == 0
    codes = json.loads((out / "codes.json").read_text())
    assert len(codes["shape"]) > 0 and len(codes["color"]) > 0
    params, grid, scene, field, meta = load_nerf(out / "nerf.safetensors")
    assert meta["codes"]["shape"] == codes["shape"] and grid.fraction > 0
    assert len(list((out / "renders").glob("view_*.png"))) == 12
    with Image.open(out / "turntable.gif") as gif:
        assert gif.n_frames == 36
    assert (out / "mesh.glb").stat().st_size > 0


def test_invert_command_says_what_is_wrong_with_its_files(trained, tmp_path, caplog):
    pose = tmp_path / "pose.json"
    command = ["invert", "--run", str(trained[0]), "--image", str(tmp_path / "missing.png"), "--pose", str(pose), "--out", str(tmp_path / "o")]
    pose.write_text(json.dumps({"camera_angle_x": 0.9, "frames": [{"transform_matrix": np.eye(4).tolist()}]}))
    assert main(command) != 0 and "cannot read" in caplog.text
    pose.write_text(json.dumps({"camera_angle_x": 0.9, "frames": [{"transform_matrix": np.eye(4).tolist()}] * 2}))
    assert main(command) != 0 and "1 images but 2 frames" in caplog.text


def test_generalization_table_scores_every_row_above_the_floor_and_draws_renders(trained, chairs, tmp_path):
    cfg = GeneralizationConfig(objects=1, tto=TTOConfig(**FAST), fit_steps=30, grid_rows=1, grid_poses=(0, 5))
    out = tmp_path / "generalization.json"
    report = generalization(trained[0], chairs, cfg, out=out)
    assert set(report["rows"]) == {"tto", "single_view_fit", "nearest", "mean_code"}
    for row, q in report["rows"].items():
        assert all(math.isfinite(q[k]) for k in ("psnr", "psnr_fg", "ssim", "fid")), row
    assert report["rows"]["tto"]["psnr"] > report["floor_psnr"] + 1.0
    with Image.open(out.with_suffix(".png")) as grid:
        assert grid.size[0] > 0
    assert json.loads(out.read_text())["objects"] == 1


def test_generalization_command_rejects_bad_rows_and_rounds(trained, chairs, tmp_path, capsys):
    command = ["eval", "generalization", "--run", str(trained[0]), "--data", str(chairs), "--json", str(tmp_path / "g.json")]
    assert main([*command, "--rows", "tto,bogus"]) == 2 and "unknown rows" in capsys.readouterr().err
    assert main([*command, "--denoise-rounds", "0"]) == 2 and "--denoise-rounds must be at least 1" in capsys.readouterr().err
    assert not (tmp_path / "g.json").exists()


# ---------------------------------------------------------------------------------------------
# Poses


def test_axis_angle_is_a_rotation_smooth_at_zero():
    from model.optimize.pose import axis_angle_to_matrix

    w = torch.tensor([[0.0, 0.0, 0.0], [1e-7, 0.0, 0.0], [0.0, 0.0, math.pi / 2]], requires_grad=True)
    r = axis_angle_to_matrix(w)
    assert torch.allclose(r[0], torch.eye(3)) and torch.allclose(r[2] @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    assert torch.allclose(r.transpose(1, 2) @ r, torch.eye(3).expand(3, 3, 3), atol=1e-6)
    r.sum().backward()
    assert torch.isfinite(w.grad).all()


def test_perturbed_pose_is_off_by_the_angle_asked_for():
    from model.optimize.pose import perturb_pose, rotation_error_deg

    pose = torch.tensor(look_at(np.array([1.5, -1.0, 0.8])), dtype=torch.float32)
    turned = perturb_pose(pose, 10.0, torch.Generator().manual_seed(0))
    assert float(rotation_error_deg(pose, turned)) == pytest.approx(10.0, abs=1e-3)


def test_pose_refinement_moves_the_pose_and_stays_finite(prior, unseen):
    from model.optimize.pose import perturb_pose

    held, _ = unseen
    view = held.subset([0])
    rough = perturb_pose(view.c2w[0], 10.0, torch.Generator().manual_seed(1))[None]
    result = invert(prior.net, prior.scene, view.images, rough, view.cameras, TTOConfig(**{**FAST, "steps": 15}, refine_pose=True))
    assert _finite(result) and not torch.allclose(result.c2w, rough)


def test_unknown_pose_is_searched_then_refined(prior, unseen):
    held, _ = unseen
    view = held.subset([0])
    cfg = TTOConfig(**{**FAST, "steps": 10}, search_azimuths=4, search_elevations=(30.0,), search_codes=2)
    result = invert(prior.net, prior.scene, view.images, None, view.cameras, cfg)
    assert _finite(result) and result.c2w.shape == (1, 4, 4)
    assert float(result.c2w[0, :3, 3].norm()) == pytest.approx(2.0, abs=0.2)
    with pytest.raises(TTOError, match="one image"):
        invert(prior.net, prior.scene, held.images[:2], None, held.cameras[:2], cfg)


def test_a_mirrored_view_sees_the_mirrored_point_at_the_flipped_pixel(prior):
    from model.nerf.rays import project
    from model.optimize.tto import with_mirrored_views

    camera = Intrinsics(20, 16, 18.0, 18.0, 9.0, 8.5)
    pose = torch.tensor(look_at(np.array([1.3, -1.2, 0.7])), dtype=torch.float32)[None]
    rgba = torch.rand(1, 16, 20, 4)
    images, c2w, cameras = with_mirrored_views(rgba, pose, [camera], prior.scene)
    assert images.shape[0] == 2 and torch.equal(images[1], rgba[0].flip(1))
    rotation = c2w[1, :3, :3]
    assert torch.allclose(rotation.T @ rotation, torch.eye(3), atol=1e-6) and float(torch.det(rotation)) == pytest.approx(1.0, abs=1e-5)
    points = torch.tensor([[0.1, 0.2, -0.1], [-0.3, 0.05, 0.2]])
    mirrored = points * torch.tensor([-1.0, 1.0, 1.0])

    def pixels(c2w_one, cam, pts):
        local = (pts - c2w_one[:3, 3]) @ c2w_one[:3, :3]
        x, y, _ = project(local, cam)
        return x, y

    x, y = pixels(c2w[0], cameras[0], points)
    xm, ym = pixels(c2w[1], cameras[1], mirrored)
    assert torch.allclose(xm, camera.width - x, atol=1e-4) and torch.allclose(ym, y, atol=1e-4)
