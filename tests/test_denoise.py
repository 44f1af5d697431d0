"""Denoise and finetune on tiny configs: the VQ-VAE-2-style denoiser (shapes, straight-through
quantiser, codebook updates), its training on renders of a tiny prior (learning, render cache,
exact resume, the command), its file format, and the finetune of a NeRF on (denoised) views,
including all-white and all-black inputs."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from model.cli.main import main
from model.data.dataset import load_views
from model.denoise.finetune import (
    DenoiseConfig,
    FinetuneConfig,
    anchor_loss,
    denoise_and_finetune,
    denoise_and_finetune_prior,
    finetune_on_views,
    ring_poses,
)
from model.denoise.io import (
    DENOISER_META,
    DENOISER_WEIGHTS,
    load_denoiser,
    save_denoiser,
)
from model.denoise.quantize import VectorQuantizer
from model.denoise.vqvae import (
    VQVAE2Denoiser,
    denoise_renders,
    rgba_channels,
    straight_rgba,
    tiny_config,
)
from model.eval.metrics import image_quality
from model.nerf.occupancy import OccupancyConfig
from model.nerf.renderer import RenderConfig, render_image
from model.prior.codes import generate, generated_grid
from model.prior.io import load_prior
from model.train import denoiser as denoiser_training
from model.train.denoiser import (
    DenoiserTrainConfig,
    PairsConfig,
    as_channels,
    cached_pairs,
    denoiser_loss,
    train_denoiser,
    training_batch,
)

TINY_PAIRS = PairsConfig(clean_views=2, perturbed_nerfs=1, perturbed_views=2, validation_instances=2, validation_views=2)


def tiny_training(steps: int, **kw) -> DenoiserTrainConfig:
    return DenoiserTrainConfig(denoiser=tiny_config(), pairs=TINY_PAIRS, steps=steps, batch=4, crop=0, lr=1e-2,
                               validate_every=kw.pop("validate_every", 20), checkpoint_every=kw.pop("checkpoint_every", 1000), log_every=1, **kw)


def tiny_finetune(steps: int, **kw) -> FinetuneConfig:
    return FinetuneConfig(steps=steps, rays_per_step=512, lr=1e-2, occupancy=OccupancyConfig(resolution=64, warmup_steps=8, update_every=8), **kw)


@pytest.fixture(scope="module")
def denoiser_run(trained, chairs, tmp_path_factory):
    """A tiny denoiser trained for 40 steps on renders of the tiny prior: (folder, summary)."""
    out = tmp_path_factory.mktemp("denoiser")
    summary = train_denoiser(trained[0], chairs, out, tiny_training(40), progress=False)
    return out, summary


@pytest.fixture(scope="module")
def instance(trained, chairs):
    """The tiny prior's NeRF of instance 0 with its grid, and that instance's training views."""
    prior = load_prior(trained[0])
    params = generate(prior.net, 0)
    views = load_views(Path(chairs) / prior.instances[0]["id"], split="train")
    return prior, params, generated_grid(params, prior.net.cfg.field, prior.scene), views


# ---------------------------------------------------------------------------------------------
# The network


@pytest.mark.parametrize("skip", [4, 0])
def test_untrained_denoiser_is_the_identity_at_any_size(skip):
    torch.manual_seed(0)
    net = VQVAE2Denoiser(replace(tiny_config(), skip_channels=skip))
    for shape in ((2, 4, 32, 32), (1, 4, 30, 27)):
        x = torch.rand(shape)
        out = net(x)
        assert out.image.shape == shape and torch.isfinite(out.latent_loss)
        assert torch.allclose(out.image, x.clamp(1e-3, 1 - 1e-3), atol=1e-5)
    with pytest.raises(ValueError, match=r"\[B, 4, H, W\]"):
        net(torch.rand(1, 3, 32, 32))


def test_quantiser_passes_gradients_straight_through_and_commits():
    torch.manual_seed(0)
    vq = VectorQuantizer(8, 4, commitment=0.25, ema=True).eval()
    z = torch.randn(2, 4, 3, 5, requires_grad=True)
    out = vq(z)
    entries = vq.codebook[out.codes].permute(0, 3, 1, 2)
    assert torch.allclose(out.quantized, entries, atol=1e-6)  # forward: the nearest entries
    out.quantized.sum().backward()
    assert torch.allclose(z.grad, torch.ones_like(z))  # backward: the identity
    z.grad = None
    vq(z).loss.backward()
    assert torch.allclose(z.grad, 2 * 0.25 * (z - entries).detach() / z.numel(), atol=1e-7)


def test_codebooks_learn_by_moving_average_or_by_gradient():
    torch.manual_seed(0)
    target = torch.full((1, 2, 4, 4), 3.0)  # every vector the same, far from the initial entries
    ema = VectorQuantizer(4, 2, ema=True, decay=0.5).train()
    for _ in range(20):
        ema(target)
    assert (ema.codebook - 3.0).norm(dim=1).min() < 1e-2
    learned = VectorQuantizer(4, 2, ema=False).train()
    learned(target)  # the codebook starts at these vectors
    learned(target + 1.0).loss.backward()
    chosen = learned.codebook.grad.abs().sum(dim=1) > 0
    assert chosen.any() and (learned.codebook.grad[chosen] < 0).all()  # a gradient step moves the entry towards the data


def test_codebook_starts_at_the_data_and_unused_entries_restart():
    torch.manual_seed(0)
    z = torch.randn(1, 2, 8, 8)
    frozen = VectorQuantizer(16, 2, ema=True, decay=1.0).train()  # decay 1: the entries stay where they start
    frozen(z)
    assert max((frozen.codebook[i] - z.flatten(2)[0].t()).norm(dim=1).min() for i in range(16)) < 1e-6  # each entry is a batch vector
    vq = VectorQuantizer(16, 2, ema=True, decay=0.5, restart_below=0.5, use_decay=0.5).train()
    vq(z)
    moved = z + 10.0  # the latents move away: entries nobody picks are restarted among them
    for _ in range(6):
        vq(moved)
    assert (vq.codebook - 10.0).norm(dim=1).max() < 5.0


def test_training_crops_inputs_and_targets_alike():
    images = torch.randint(0, 256, (3, 32, 32, 4), dtype=torch.uint8)
    cfg = replace(tiny_training(1), batch=5, crop=12)
    x, y = training_batch({"inputs": images, "targets": images}, cfg, torch.Generator().manual_seed(0))
    assert x.shape == y.shape == (5, 4, 12, 12) and torch.equal(x, y) and 0 <= x.min() and x.max() <= 1


def test_the_tto_share_draws_batch_elements_from_the_tto_pairs():
    # 6 pairs of the prior's renders (value 0) then 2 TTO pairs (value 255): whole images, no crop
    images = torch.cat([torch.zeros(6, 8, 8, 4, dtype=torch.uint8), torch.full((2, 8, 8, 4), 255, dtype=torch.uint8)])
    pairs = {"inputs": images, "targets": images, "tto_pairs": torch.tensor(2)}

    def tto_fraction(share: float) -> float:
        cfg = replace(tiny_training(1), batch=400, crop=0, tto_share=share)
        x, _ = training_batch(pairs, cfg, torch.Generator().manual_seed(0))
        return float((x.flatten(1).mean(1) > 0.5).float().mean())

    assert tto_fraction(1.0) == 1.0 and tto_fraction(0.0) == pytest.approx(0.25, abs=0.07)
    assert tto_fraction(0.5) == pytest.approx(0.5, abs=0.08)
    with pytest.raises(ValueError, match="TTO share"):
        from model.train.denoiser import train_denoiser

        train_denoiser(Path("unused"), Path("unused"), Path("unused"), replace(tiny_training(1), tto_share=1.5))


def test_rgba_layout_round_trips():
    rgba = torch.rand(2, 8, 8, 4)
    rgba[0, :2, :, 3] = 0.0
    back = straight_rgba(rgba_channels(rgba))
    visible = rgba[..., 3] > 1e-3
    assert torch.allclose(back[..., 3], rgba[..., 3]) and torch.allclose(back[visible][:, :3], rgba[visible][:, :3], atol=1e-5)


# ---------------------------------------------------------------------------------------------
# Training and the file format


def test_training_reduces_the_loss_and_writes_the_denoiser(trained, chairs, denoiser_run):
    out, summary = denoiser_run
    pairs = cached_pairs(trained[0], chairs, out, TINY_PAIRS, progress=False)
    x, y = as_channels(pairs["inputs"]), as_channels(pairs["targets"])
    denoiser, meta = load_denoiser(out)
    with torch.no_grad():
        after = torch.mean((denoiser(x).image - y) ** 2)
    assert after < 0.99 * torch.mean((x - y) ** 2)  # the untrained denoiser is the identity
    assert summary["steps"] == 40 and summary["pairs"] == len(x) and math.isfinite(summary["final"]["val_psnr"])
    assert meta["summary"] == summary and (out / DENOISER_WEIGHTS).is_file() and (out / DENOISER_META).is_file()
    assert not list(out.rglob("*.pt")) and not list(out.rglob("*.pkl"))  # nothing pickled


def test_denoiser_learns_to_undo_a_haze():
    torch.manual_seed(0)
    net = VQVAE2Denoiser(tiny_config())
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-2)
    clean = torch.rand(8, 4, 16, 16)
    hazy = 0.7 * clean + 0.3  # washed out towards white, as a cloud of density renders
    first = None
    for _ in range(100):
        loss, info = denoiser_loss(net, hazy, clean, 1.0)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        first = first if first is not None else float(info["mse"])
    assert float(info["mse"]) < 0.3 * first


def test_renders_are_cached_and_resume_continues_exactly(trained, chairs, denoiser_run, tmp_path, monkeypatch):
    out, _ = denoiser_run
    cached = tmp_path / "resumed"
    (cached / "pairs").mkdir(parents=True)
    for path in (out / "pairs").iterdir():
        (cached / "pairs" / path.name).write_bytes(path.read_bytes())

    def no_rendering(*args, **kwargs):
        raise AssertionError("cached pairs were rendered again")

    monkeypatch.setattr(denoiser_training, "instance_pairs", no_rendering)
    monkeypatch.setattr(denoiser_training, "validation_pairs", no_rendering)
    assert train_denoiser(trained[0], chairs, cached, tiny_training(40), until=15, progress=False) == {}
    train_denoiser(trained[0], chairs, cached, tiny_training(40), resume=True, progress=False)
    a, _ = load_denoiser(out)
    b, _ = load_denoiser(cached)
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.equal(x, y), name
    with pytest.raises(ValueError, match="another prior or other pair settings"):
        train_denoiser(trained[0], chairs, cached, replace(tiny_training(40), pairs=replace(TINY_PAIRS, clean_views=3)), progress=False)


def test_tto_pairs_render_unseen_validation_objects_against_their_ground_truth(trained, chairs, denoiser_run, tmp_path, monkeypatch):
    from model.data.dataset import load_index

    out, _ = denoiser_run
    (tmp_path / "pairs").mkdir()
    for path in (out / "pairs").iterdir():
        (tmp_path / "pairs" / path.name).write_bytes(path.read_bytes())
    base = cached_pairs(trained[0], chairs, tmp_path, TINY_PAIRS, progress=False)
    with_tto = replace(TINY_PAIRS, tto_objects=1, tto_views=3)
    pairs = cached_pairs(trained[0], chairs, tmp_path, with_tto, progress=False)  # the other renders stay valid
    assert len(pairs["inputs"]) == len(base["inputs"]) + 3 and torch.equal(pairs["inputs"][: len(base["inputs"])], base["inputs"])
    val = [e.id for e in load_index(chairs) if e.split == "val"]
    assert (tmp_path / "pairs" / f"tto-{val[0]}.safetensors").is_file()
    truth = load_views(chairs / val[0], "train")
    expected = rgba_channels(truth.images[denoiser_training.spread(3, len(truth.files))]).permute(0, 2, 3, 1)
    got = as_channels(pairs["targets"][-3:]).permute(0, 2, 3, 1)
    assert (got - expected).abs().max() <= 1 / 255 + 1e-6  # the ground truth of the object's own views
    rendered = as_channels(pairs["inputs"][-3:])
    assert torch.isfinite(rendered).all() and float(rendered[:, 3].mean()) > 0.01  # TTO's NeRF shows an object
    # a second input view: one more TTO of the same object, from another test view, against the same ground truth
    second = denoiser_training.tto_input_views(chairs, val[0], 2)[1]
    more = cached_pairs(trained[0], chairs, tmp_path, replace(with_tto, tto_inputs=2), progress=False)
    assert second > 0 and (tmp_path / "pairs" / denoiser_training.tto_pairs_file(val[0], second)).is_file()
    assert len(more["inputs"]) == len(pairs["inputs"]) + 3 and torch.equal(more["inputs"][: len(pairs["inputs"])], pairs["inputs"])
    assert torch.equal(more["targets"][-3:], pairs["targets"][-3:]) and not torch.equal(more["inputs"][-3:], pairs["inputs"][-3:])
    monkeypatch.setattr(denoiser_training, "tto_object_pairs", lambda *a, **k: (_ for _ in ()).throw(AssertionError("rendered again")))
    assert torch.equal(cached_pairs(trained[0], chairs, tmp_path, with_tto, progress=False)["inputs"], pairs["inputs"])
    with pytest.raises(ValueError, match="TTOs per TTO object"):
        cached_pairs(trained[0], chairs, tmp_path, replace(with_tto, tto_inputs=0), progress=False)
    with pytest.raises(ValueError, match="TTO renders of other settings"):
        cached_pairs(trained[0], chairs, tmp_path, replace(with_tto, tto_views=2), progress=False)
    with pytest.raises(ValueError, match="outside its test split that the prior did not train on"):
        cached_pairs(trained[0], chairs, tmp_path / "other", replace(TINY_PAIRS, tto_objects=len(val) + 1), progress=False)


def test_resume_without_checkpoint_says_what_to_do(trained, chairs, tmp_path):
    with pytest.raises(FileNotFoundError, match="without --resume"):
        train_denoiser(trained[0], chairs, tmp_path, tiny_training(5), resume=True, progress=False)


def test_save_load_round_trip(tmp_path):
    torch.manual_seed(0)
    net = VQVAE2Denoiser(tiny_config()).train()
    net(torch.rand(4, 4, 32, 32))  # move the moving-average codebooks off their start
    with torch.no_grad():
        net.decode[-1].weight.normal_()
    save_denoiser(tmp_path / "d", net.eval(), {"note": "test"})
    loaded, meta = load_denoiser(tmp_path / "d")
    x = torch.rand(2, 4, 32, 32)
    assert torch.equal(net(x).image, loaded(x).image) and meta["note"] == "test" and loaded.cfg == net.cfg
    with pytest.raises(FileNotFoundError, match="train-denoiser"):
        load_denoiser(tmp_path / "missing")


def test_cli_trains_a_denoiser(trained, chairs, tmp_path):
    out = tmp_path / "cli"
    args = ["train-denoiser", "--run", str(trained[0]), "--data", str(chairs), "--out", str(out), "--steps", "2", "--batch", "2",
            "--crop", "0", "--clean-views", "1", "--perturbed-nerfs", "0", "--validate-every", "0"]
    assert main(args) == 0
    _, meta = load_denoiser(out)
    assert meta["summary"]["steps"] == 2 and meta["prior"]["sha256"]
    assert main([*args[:-2], "--validate-every", "-1"]) == 2  # a clear error, not a traceback


# ---------------------------------------------------------------------------------------------
# Finetune


def _views_psnr(prior, params, views) -> float:
    grid = generated_grid(params, prior.net.cfg.field, prior.scene)
    renders = torch.stack([render_image(params, prior.net.cfg.field, c, cam, RenderConfig(), scene=prior.scene, grid=grid)["rgb"] for c, cam in zip(views.c2w, views.cameras)])
    return image_quality(renders, views.images)["psnr"]


def test_finetune_improves_its_views_and_stays_near_the_start(instance):
    prior, params, grid, views = instance
    subset = views.subset(slice(0, 8))
    before = _views_psnr(prior, params, subset)
    records = []
    tuned = finetune_on_views(params, prior.net.cfg.field, prior.scene, subset.images, subset.c2w, subset.cameras, tiny_finetune(60),
                              grid=grid, progress=records.append)
    assert all(torch.isfinite(v).all() for v in tuned.values()) and set(tuned) == set(params)
    assert _views_psnr(prior, tuned, subset) > before + 0.5
    assert records[-1]["step"] == 59 and all(math.isfinite(r["loss"]) for r in records)
    # a stronger pull keeps the parameters closer to where they started
    pulled = finetune_on_views(params, prior.net.cfg.field, prior.scene, subset.images, subset.c2w, subset.cameras, tiny_finetune(60, anchor_weight=1e3), grid=grid)
    assert anchor_loss(pulled, params) < anchor_loss(tuned, params)


@pytest.mark.parametrize("colour", [0.0, 1.0])
def test_all_black_and_all_white_images_stay_finite(instance, denoiser_run, colour):
    prior, params, grid, views = instance
    denoiser, _ = load_denoiser(denoiser_run[0])
    height, width = views.height, views.width
    rgb = torch.full((2, height, width, 3), colour)
    opacity = torch.full((2, height, width), 1.0 - colour)  # black: opaque; white: empty
    denoised = denoise_renders(denoiser, rgb, opacity)
    assert denoised.shape == (2, height, width, 4) and torch.isfinite(denoised).all() and denoised.min() >= 0 and denoised.max() <= 1
    images = torch.cat([torch.full((2, height, width, 3), colour), opacity[..., None]], dim=-1)
    tuned = finetune_on_views(params, prior.net.cfg.field, prior.scene, images, views.c2w[:2], views.cameras[:2], tiny_finetune(10), grid=grid)
    assert all(torch.isfinite(v).all() for v in tuned.values())


def test_finetune_rejects_bad_views(instance):
    prior, params, _, views = instance
    with pytest.raises(ValueError, match="RGBA"):
        finetune_on_views(params, prior.net.cfg.field, prior.scene, views.images[:2, ..., :3], views.c2w[:2], views.cameras[:2], tiny_finetune(1))
    bad = views.c2w[:2].clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        finetune_on_views(params, prior.net.cfg.field, prior.scene, views.images[:2], bad, views.cameras[:2], tiny_finetune(1))


def test_denoise_and_finetune_end_to_end(instance, denoiser_run):
    prior, params, grid, views = instance
    denoiser, _ = load_denoiser(denoiser_run[0])
    poses = ring_poses(elevations=(30.0,), per_ring=4)
    assert poses.shape == (4, 4, 4) and torch.allclose(poses[:, :3, 3].norm(dim=1), torch.full((4,), 2.0))
    result = denoise_and_finetune(params, prior.net.cfg.field, prior.scene, denoiser, poses, views.camera,
                                  DenoiseConfig(finetune=tiny_finetune(10)), grid=grid)
    assert result.renders.shape == (4, views.height, views.width, 3) and result.denoised.shape == (4, views.height, views.width, 4)
    assert all(torch.isfinite(v).all() for v in result.params.values()) and result.grid.fraction > 0
    assert result.timings["total_s"] >= result.timings["finetune_s"] > 0
    run = denoise_and_finetune_prior(denoiser_run[0], DenoiseConfig(finetune=tiny_finetune(5)), ring_poses(elevations=(30.0,), per_ring=2))
    tuned, tuned_grid = run(prior, params)
    assert set(tuned) == set(params) and tuned_grid.resolution == 64
    with pytest.raises(ValueError, match=r"\[m, 4, 4\]"):
        denoise_and_finetune(params, prior.net.cfg.field, prior.scene, denoiser, poses[0], views.camera, DenoiseConfig())
    with pytest.raises(ValueError, match="elevations"):
        ring_poses(elevations=(90.0,))


def test_each_round_denoises_and_finetunes_the_nerf_the_round_before_finetuned(instance, denoiser_run):
    prior, params, grid, views = instance
    denoiser, _ = load_denoiser(denoiser_run[0])
    field, poses = prior.net.cfg.field, ring_poses(elevations=(30.0,), per_ring=2)
    reports = []
    two = denoise_and_finetune(params, field, prior.scene, denoiser, poses, views.camera, DenoiseConfig(finetune=tiny_finetune(3, progress_every=1), rounds=2),
                               grid=grid, progress=reports.append)
    first = denoise_and_finetune(params, field, prior.scene, denoiser, poses, views.camera, DenoiseConfig(finetune=tiny_finetune(3), rounds=1), grid=grid)
    second = denoise_and_finetune(first.params, field, prior.scene, denoiser, poses, views.camera, DenoiseConfig(finetune=tiny_finetune(3), rounds=1),
                                  grid=first.grid)
    assert all(torch.allclose(two.params[k], second.params[k], atol=1e-6) for k in params)
    assert not all(torch.allclose(two.params[k], first.params[k], atol=1e-6) for k in params)
    assert torch.allclose(two.denoised, second.denoised, atol=1e-6)  # the last round's views
    assert [r["step"] for r in reports] == list(range(6)) and {r["steps"] for r in reports} == {6}
    assert DenoiseConfig(finetune=tiny_finetune(3), rounds=2).total_steps == 6
    with pytest.raises(ValueError, match="at least one round"):
        DenoiseConfig(rounds=0)


def test_input_views_make_up_their_share_of_the_finetune_views(instance, denoiser_run):
    from model.denoise.finetune import with_inputs
    from model.optimize.step import RayBatch

    prior, params, grid, views = instance

    def pool(count: int, fill: float = 0.0) -> RayBatch:
        return RayBatch(torch.full((count, 3), fill), torch.full((count, 3), fill), torch.full((count, 4), fill))

    denoised, photo = pool(16 * 64), pool(64, 1.0)  # 16 denoised views, one photo of the same size
    assert with_inputs(denoised, None, 0.5) is denoised and with_inputs(denoised, photo, 0.0) is denoised
    rays = with_inputs(denoised, photo, 0.5)
    assert len(rays) == 32 * 64 and torch.equal(rays.rgba[: 16 * 64], denoised.rgba) and bool((rays.rgba[16 * 64 :] == 1).all())
    # a photo of another size weighs by its share, not its pixel count; a tiny share keeps one copy
    assert len(with_inputs(denoised, pool(256, 1.0), 0.5)) == 32 * 64
    assert len(with_inputs(denoised, pool(128), 0.01)) == 16 * 64 + 128
    with pytest.raises(ValueError, match="input_share"):
        DenoiseConfig(input_share=1.0)
    # end to end: the NeRF's own training view joins the denoised ones
    denoiser, _ = load_denoiser(denoiser_run[0])
    poses = ring_poses(elevations=(30.0,), per_ring=2)
    result = denoise_and_finetune(params, prior.net.cfg.field, prior.scene, denoiser, poses, views.camera,
                                  DenoiseConfig(finetune=tiny_finetune(5)), grid=grid, inputs=(views.images[:1], views.c2w[:1], views.cameras[:1]))
    assert all(torch.isfinite(v).all() for v in result.params.values()) and result.grid.fraction > 0
    with pytest.raises(ValueError, match="as many poses and cameras"):
        denoise_and_finetune(params, prior.net.cfg.field, prior.scene, denoiser, poses, views.camera, DenoiseConfig(finetune=tiny_finetune(1)),
                             grid=grid, inputs=(views.images[:1], views.c2w[:2], views.cameras[:1]))


def test_invert_command_searches_the_pose_then_denoises_and_finetunes(trained, chairs, denoiser_run, tmp_path, caplog):
    from model.prior.outputs import load_nerf
    from PIL import Image

    from model.data.dataset import load_index

    object_id = next(e.id for e in load_index(chairs) if e.split == "test")
    held = load_views(Path(chairs) / object_id, "test")
    image = tmp_path / "photo.png"
    Image.fromarray((held.images[0].numpy() * 255).round().astype(np.uint8), "RGBA").save(image)
    out = tmp_path / "inverted"
    command = ["invert", "--run", str(trained[0]), "--image", str(image), "--out", str(out), "--steps", "8", "--rays", "256", "--mesh-resolution", "24"]
    assert main([*command, "--denoise"]) != 0 and "--denoiser" in caplog.text
    assert main([*command, "--init", "query"]) != 0 and "--query" in caplog.text
    assert main([*command, "--image", str(image)]) != 0 and "without --pose give exactly one --image" in caplog.text
    assert main([*command, "--fov", "200"]) != 0 and "--fov is a horizontal field of view" in caplog.text
    assert main([*command, "--pose", str(tmp_path / "pose.json"), "--fov", "40"]) != 0 and "the pose file gives the camera" in caplog.text
    assert main([*command, "--denoise", "--denoiser", str(denoiser_run[0]), "--denoise-rounds", "0"]) != 0 and "--denoise-rounds must be at least 1" in caplog.text
    assert main([*command, "--no-denoise-mirror"]) != 0 and "--denoise-mirror: denoise-and-finetune settings, used only with --denoise" in caplog.text
    assert main([*command, "--denoise", "--denoiser", str(denoiser_run[0]), "--denoise-steps", "6", "--denoise-rounds", "2", "--denoise-mirror"]) == 0
    params, grid, _, _, meta = load_nerf(out / "nerf.safetensors")
    assert meta["denoised"] and meta["pose"] == "searched" and grid.fraction > 0
    assert meta["denoise"]["rounds"] == 2 and meta["denoise"]["finetune"]["steps"] == 6 and meta["denoise"]["mirror_inputs"] is True
    assert all(torch.isfinite(v).all() for v in params.values())
    pose = json.loads((out / "pose.json").read_text())["frames"][0]
    c2w = np.array(pose["transform_matrix"])
    assert c2w.shape == (4, 4) and np.allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-4)
    assert np.linalg.norm(c2w[:3, 3]) > 0.9  # a camera outside the unit box, looking in
    assert len(list((out / "renders").glob("view_*.png"))) == 12 and (out / "mesh.glb").stat().st_size > 0


def test_mirrored_inputs_join_the_finetune_views_beside_the_photo(instance, denoiser_run, monkeypatch):
    import model.denoise.finetune as finetune_module
    from model.optimize.fit import training_rays
    from model.optimize.tto import with_mirrored_views

    prior, params, grid, views = instance
    denoiser, _ = load_denoiser(denoiser_run[0])
    seen = []
    real = finetune_module.finetune_on_rays

    def recording(params, field, scene, rays, cfg, **kwargs):
        seen.append(rays)
        return real(params, field, scene, rays, cfg, **kwargs)

    monkeypatch.setattr(finetune_module, "finetune_on_rays", recording)
    poses, photo = ring_poses(elevations=(30.0,), per_ring=4), (views.images[:1], views.c2w[:1], views.cameras[:1])
    for mirror in (False, True):
        denoise_and_finetune(params, prior.net.cfg.field, prior.scene, denoiser, poses, views.camera,
                             DenoiseConfig(finetune=tiny_finetune(2), rounds=1, mirror_inputs=mirror), grid=grid, inputs=photo)
    plain, mirrored = seen
    pixels = views.height * views.width
    assert len(plain) == len(mirrored) == 8 * pixels  # 4 denoised views, the inputs repeated to half
    photo_rays = training_rays(finetune_module.posed_views(*photo, prior.scene, "cpu"), "cpu")
    assert torch.equal(plain.rgba[4 * pixels :], photo_rays.rgba.repeat(4, 1))
    # the photo and its mirror image share the copies: the flipped image seen by the reflected camera
    both = training_rays(finetune_module.posed_views(*with_mirrored_views(*photo, prior.scene), prior.scene, "cpu"), "cpu")
    assert torch.equal(both.rgba[pixels:], photo[0][0].flip(1).reshape(-1, 4))
    for field_name in ("origins", "directions", "rgba"):
        assert torch.allclose(getattr(mirrored, field_name)[4 * pixels :], getattr(both, field_name).repeat(2, 1))


def test_an_input_photo_of_another_size_joins_the_finetune_views(instance, denoiser_run):
    from model.nerf.rays import Intrinsics

    prior, params, grid, views = instance
    denoiser, _ = load_denoiser(denoiser_run[0])
    # a non-square photo at another resolution than the ring renders, its camera scaled with it
    height, width = views.height + 8, views.width - 6
    photo = torch.nn.functional.interpolate(views.images[:1].permute(0, 3, 1, 2), size=(height, width), mode="bilinear").permute(0, 2, 3, 1)
    camera = views.cameras[0]
    scaled = Intrinsics(width, height, camera.fx * width / camera.width, camera.fy * height / camera.height,
                        camera.cx * width / camera.width, camera.cy * height / camera.height)
    for mirror in (False, True):
        result = denoise_and_finetune(params, prior.net.cfg.field, prior.scene, denoiser, ring_poses(elevations=(30.0,), per_ring=2), views.camera,
                                      DenoiseConfig(finetune=tiny_finetune(5), rounds=1, mirror_inputs=mirror), grid=grid,
                                      inputs=(photo, views.c2w[:1], [scaled]))
        assert all(torch.isfinite(v).all() for v in result.params.values()) and result.grid.fraction > 0
