"""Datasets: format round trip, ground-truth rendering, procedural chairs, mesh and Sweet Home 3D imports."""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from model.data import sh3d
from model.data.build import RenderSettings, build_dataset
from model.data.cameras import CAMERA_ANGLE_X, RADIUS, evaluation_poses, fibonacci_hemisphere, training_poses
from model.cli.data import register
from model.data.dataset import (
    OBJECT_SPLITS,
    DatasetError,
    assign_splits,
    load_index,
    load_views,
    validate_views,
)
from model.data.imports import mesh_file_objects, read_captions
from model.data.meshes import normalise
from model.data.raycast import render_views
from model.data.synth import chair_mesh, sample_spec, synth_objects
from model.nerf.rays import focal_from_fov
from model.nerf.scene import UNIT_BOX

TINY = RenderSettings(views=6, resolution=24)


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth")
    build_dataset(root, synth_objects(3, seed=7), TINY)
    return root


def _copy_object(synth_root: Path, tmp_path: Path) -> Path:
    object_id = load_index(synth_root)[0].id
    return Path(shutil.copytree(synth_root / object_id, tmp_path / object_id))


# ---------------------------------------------------------------------------------------------
# Cameras


def test_training_poses_cover_the_upper_hemisphere_deterministically():
    for count in (1, 6, 91):
        directions = fibonacci_hemisphere(count)
        assert directions.shape == (count, 3)
        assert np.allclose(np.linalg.norm(directions, axis=1), 1.0)
        assert (directions[:, 2] > 0).all()
    assert np.array_equal(training_poses(91), training_poses(91))
    train = training_poses(91)[:, :3, 3] / RADIUS
    test = evaluation_poses()[:, :3, 3] / RADIUS
    # Evaluation poses lie between training poses.
    gap = np.degrees(np.arccos(np.clip(test @ train.T, -1, 1))).min(axis=1)
    assert (gap > 5.0).all()


# ---------------------------------------------------------------------------------------------
# Synthetic chairs and the format


def test_synth_dataset_reads_back(synth_root):
    index = load_index(synth_root)
    assert len(index) == 3
    assert sorted(e.split for e in index) == sorted(OBJECT_SPLITS)
    for entry in index:
        assert entry.category == "chair" and entry.caption.startswith("a ") and "chair" in entry.caption
        assert entry.extra["source"] == "synth" and "attributes" in entry.extra
        views = load_views(synth_root / entry.id, split="train")
        assert views.images.shape == (6, 24, 24, 4) and views.images.dtype == torch.float32
        assert views.c2w.shape == (6, 4, 4)
        assert views.width == views.height == 24
        assert views.camera.fx == views.camera.fy == pytest.approx(0.5 * 24 / 0.5)
        assert (views.camera.cx, views.camera.cy) == (12.0, 12.0)
        assert views.scene == UNIT_BOX
        alpha = views.images[..., 3]
        assert (alpha == 0).any() and (alpha == 1).any()
        # Every training camera sees the object.
        assert (alpha.flatten(1).amax(dim=1) == 1).all()
        rotation = views.c2w[:, :3, :3].double()
        assert torch.allclose(rotation @ rotation.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(6, 3, 3), atol=1e-5)
        assert torch.allclose(torch.linalg.det(rotation), torch.ones(6, dtype=torch.float64), atol=1e-5)
        position = views.c2w[:, :3, 3].double()
        assert torch.allclose(position.norm(dim=1), torch.full((6,), RADIUS, dtype=torch.float64), atol=1e-5)
        # The camera looks down its -Z axis at the origin.
        forward = -rotation[:, :, 2]
        assert torch.allclose(forward, -position / position.norm(dim=1, keepdim=True), atol=1e-5)
        test = load_views(synth_root / entry.id, split="test")
        assert test.images.shape[0] == len(evaluation_poses())
        assert len(load_views(synth_root / entry.id, split=None).files) == 6 + len(evaluation_poses())
        mesh = trimesh.load(views.mesh_path)
        extent = mesh.bounds[1] - mesh.bounds[0]
        assert extent.max() == pytest.approx(0.9, abs=1e-6)
        assert np.allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-6)


def _project(points: torch.Tensor, c2w: torch.Tensor, focal: float, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel row and column of world points seen by an OpenGL-convention camera."""
    camera = (points - c2w[:3, 3]) @ c2w[:3, :3]
    x = focal * camera[:, 0] / -camera[:, 2] + 0.5 * size
    y = -focal * camera[:, 1] / -camera[:, 2] + 0.5 * size
    return y.floor().long().clamp(0, size - 1), x.floor().long().clamp(0, size - 1)


def test_surface_points_project_onto_the_rendered_silhouette():
    """Cameras, rays and rendering agree: points on the mesh project onto (or next to) covered pixels."""
    mesh = normalise(chair_mesh(sample_spec(np.random.default_rng(5))))
    poses = training_poses(6)[[1, 4]]
    size = 48
    focal = focal_from_fov(size, CAMERA_ANGLE_X)
    images = render_views(mesh, poses, size, size, focal)
    points, _ = trimesh.sample.sample_surface(mesh.to_trimesh(), 400, seed=0)
    points = torch.as_tensor(points)
    for image, pose in zip(images, torch.as_tensor(poses)):
        # Points on faces seen edge-on fall on the silhouette: allow the neighbouring pixels.
        covered = torch.nn.functional.max_pool2d(torch.as_tensor(image[None, None, :, :, 3]).float(), 3, 1, 1)[0, 0] > 0
        row, col = _project(points, pose, focal, size)
        assert covered[row, col].float().mean() > 0.995
        # A mirrored projection misses, so the check has teeth.
        assert covered[size - 1 - row, col].float().mean() < 0.9


def test_synth_is_deterministic_by_seed(tmp_path):
    settings = RenderSettings(views=2, resolution=16)
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        build_dataset(tmp_path / name, synth_objects(2, seed=seed), settings)
    index_a = json.loads((tmp_path / "a" / "index.json").read_text())
    index_b = json.loads((tmp_path / "b" / "index.json").read_text())
    assert index_a == index_b
    for entry in index_a["objects"]:
        for image in sorted((tmp_path / "a" / entry["id"] / "images").iterdir()):
            assert image.read_bytes() == (tmp_path / "b" / entry["id"] / "images" / image.name).read_bytes()
    captions_c = [e["caption"] for e in json.loads((tmp_path / "c" / "index.json").read_text())["objects"]]
    attributes_a = [e["attributes"] for e in index_a["objects"]]
    attributes_c = [e["attributes"] for e in json.loads((tmp_path / "c" / "index.json").read_text())["objects"]]
    assert attributes_a != attributes_c and all(captions_c)
    # More objects keep the first ones unchanged.
    first = next(iter(synth_objects(5, seed=3)))
    assert first.caption == index_a["objects"][0]["caption"]


def test_splits_are_deterministic_and_balanced():
    ids = [f"object-{i}" for i in range(1000)]
    splits = assign_splits(ids)
    assert splits == assign_splits(reversed(ids))
    counts = {s: list(splits.values()).count(s) for s in OBJECT_SPLITS}
    assert 700 < counts["train"] < 900 and 50 < counts["val"] < 150 and 50 < counts["test"] < 150
    for n in (3, 4, 5, 10):
        assert set(assign_splits(ids[:n]).values()) == set(OBJECT_SPLITS)
    assert set(assign_splits(["only"]).values()) <= set(OBJECT_SPLITS)


# ---------------------------------------------------------------------------------------------
# Validation


def test_load_views_rejects_nan_pose(synth_root, tmp_path):
    folder = _copy_object(synth_root, tmp_path)
    transforms = json.loads((folder / "transforms.json").read_text())
    transforms["frames"][1]["transform_matrix"][0][3] = float("nan")
    (folder / "transforms.json").write_text(json.dumps(transforms))
    with pytest.raises(DatasetError, match="NaN"):
        load_views(folder)


def test_load_views_rejects_corrupt_and_missing_files(synth_root, tmp_path):
    folder = _copy_object(synth_root, tmp_path)
    image = folder / "images" / "train_002.png"
    original = image.read_bytes()
    image.write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="train_002.png"):
        load_views(folder)
    Image.new("RGBA", (10, 10)).save(image)
    with pytest.raises(DatasetError, match="10x10"):
        load_views(folder)
    image.unlink()
    with pytest.raises(DatasetError, match="missing"):
        load_views(folder)
    image.write_bytes(original)
    load_views(folder)
    (folder / "transforms.json").write_text("{not json")
    with pytest.raises(DatasetError, match="not valid JSON"):
        load_views(folder)
    (folder / "transforms.json").unlink()
    with pytest.raises(DatasetError, match="not found"):
        load_views(folder)
    with pytest.raises(DatasetError, match="index.json"):
        load_index(tmp_path)


def test_validate_views_rejects_bad_arrays():
    images, poses = torch.rand(2, 4, 4, 4), torch.eye(4).expand(2, 4, 4).clone()
    validate_views(images, poses)
    validate_views(images.numpy(), poses.numpy())
    bad = images.clone()
    bad[1, 0, 0, 0] = float("inf")
    with pytest.raises(DatasetError, match=r"images \[1\]"):
        validate_views(bad, poses)
    bad_pose = poses.clone()
    bad_pose[0, 0, 0] = float("nan")
    with pytest.raises(DatasetError, match=r"poses \[0\]"):
        validate_views(images, bad_pose)
    with pytest.raises(DatasetError, match="one pose per image"):
        validate_views(images, poses[:1])


# ---------------------------------------------------------------------------------------------
# Imported meshes


def _textured_box(folder: Path) -> Path:
    """A Y-up box, tall along Y, whose texture is red on the -X half and blue on the +X half."""
    folder.mkdir(parents=True, exist_ok=True)
    box = trimesh.creation.box(extents=(0.4, 1.0, 0.3))
    uv = np.stack([np.where(box.vertices[:, 0] > 0, 0.75, 0.25), np.full(len(box.vertices), 0.5)], axis=1)
    texture = np.zeros((8, 8, 3), np.uint8)
    texture[:, :4], texture[:, 4:] = (220, 30, 30), (30, 30, 220)
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture))
    path = folder / "tex_box.obj"
    box.export(path)
    return path


def test_import_meshes_textured_obj_and_ply(tmp_path):
    obj = _textured_box(tmp_path / "obj")
    ball = trimesh.creation.icosphere(subdivisions=2)
    ball.visual.vertex_colors = np.tile([40, 180, 60, 255], (len(ball.vertices), 1))
    ply = tmp_path / "green_ball.ply"
    ball.export(ply)
    glb = tmp_path / "tex_box.glb"
    trimesh.load(obj, force="mesh").export(glb)
    captions = tmp_path / "captions.tsv"
    captions.write_text("# stem\tcaption\ntex_box\ta red and blue box\n")
    out = tmp_path / "out"
    build_dataset(out, mesh_file_objects([obj, ply, glb], "chair", read_captions(captions)), TINY)
    index = {entry.id: entry for entry in load_index(out)}
    assert set(index) == {"tex-box", "green-ball", "tex-box-2"}
    assert index["tex-box-2"].extra["texture"] == "tex_ok" and index["tex-box-2"].extra["file"] == "tex_box.glb"
    assert index["tex-box"].caption == "a red and blue box"
    assert index["tex-box"].extra["texture"] == "tex_ok"
    assert index["green-ball"].caption == "a green chair"
    assert index["green-ball"].extra["texture"] == "color_only"

    views = load_views(out / "tex-box", split=None)
    opaque = views.images[views.images[..., 3] == 1][:, :3]
    reddish = (opaque[:, 0] > opaque[:, 2] + 0.2).any()
    bluish = (opaque[:, 2] > opaque[:, 0] + 0.2).any()
    assert reddish and bluish
    # The Y-up source stands upright: its long side is now Z.
    extent = np.ptp(trimesh.load(views.mesh_path).vertices, axis=0)
    assert extent.argmax() == 2 and extent.max() == pytest.approx(0.9)

    ball_views = load_views(out / "green-ball")
    opaque = ball_views.images[ball_views.images[..., 3] == 1][:, :3]
    assert (opaque[:, 1] > opaque[:, 0]).all() and (opaque[:, 1] > opaque[:, 2]).all()


def test_missing_texture_falls_back_to_the_material_colour(tmp_path, caplog):
    obj = _textured_box(tmp_path / "obj")
    for png in obj.parent.glob("*.png"):
        png.unlink()
    (tmp_path / "captions.json").write_text(json.dumps({"tex_box": "a grey box"}))
    with caplog.at_level(logging.WARNING, logger="model.data.meshes"):
        build_dataset(tmp_path / "out", mesh_file_objects([obj], "box", read_captions(tmp_path / "captions.json")), TINY)
    assert "not found" in caplog.text
    assert load_index(tmp_path / "out")[0].extra["texture"] == "tex_missing"
    views = load_views(tmp_path / "out" / "tex-box")
    opaque = views.images[views.images[..., 3] == 1][:, :3]
    assert (opaque.amax(dim=1) - opaque.amin(dim=1) < 0.02).all()


def test_adding_to_a_dataset_merges_the_index(synth_root, tmp_path):
    root = Path(shutil.copytree(synth_root, tmp_path / "data"))
    ball = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=1).export(ball)
    build_dataset(root, mesh_file_objects([ball], "chair"), TINY)
    ids = load_index(root).ids()
    assert len(ids) == 4 and "ball" in ids


# ---------------------------------------------------------------------------------------------
# Sweet Home 3D


def _fake_library(folder: Path) -> Path:
    """A tiny .sh3f: a Z-up tall box model turned Y-up by its catalogue's modelRotation."""
    box = trimesh.creation.box(extents=(0.5, 0.4, 1.0))
    box.visual = trimesh.visual.ColorVisuals(box, face_colors=[200, 40, 40, 255])
    obj_text = trimesh.exchange.obj.export_obj(box, include_color=False, include_texture=False)
    catalogue = "\n".join(
        [
            "# comment",
            "id=Test#Library",
            "name=Test library",
            "license=CC0 \\",
            "    public domain",
            "id#1=Test#seat",
            "name#1=Caf\\u00e9 chair",
            "creator#1=Jane Doe",
            "model#1=/test/seat/seat.obj",
            "modelRotation#1=1 0 0 0 0 1 0 -1 0",
            "id#2=Test#lamp",
            "name#2=Lamp",
            "model#2=/test/lamp/lamp.obj",
        ]
    )
    path = folder / "Test.sh3f"
    folder.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("PluginFurnitureCatalog.properties", catalogue.encode("iso-8859-1"))
        archive.writestr("LICENSE.TXT", "Public domain: http://creativecommons.org/publicdomain/zero/1.0/\n")
        archive.writestr("test/seat/seat.obj", "mtllib seat.mtl\nusemtl red\n" + obj_text)
        archive.writestr("test/seat/seat.mtl", "newmtl red\nKd 0.8 0.1 0.1\n")
    return path


def test_sh3d_parses_a_fake_library_offline(tmp_path):
    cache = tmp_path / "cache"
    _fake_library(cache / sh3d.FURNITURE_SUBDIR)
    table = tmp_path / "categories.tsv"
    table.write_text("# test\ncategory\tlibrary\tmodel\tname\ttexture\nchair\tTest.sh3f\ttest/seat/seat.obj\tCafe chair\tcolor_only\n")

    library = sh3d.Library.open(cache / sh3d.FURNITURE_SUBDIR / "Test.sh3f")
    assert library.title == "Test library" and library.licence == "CC0 public domain"
    assert library.licence_url == "http://creativecommons.org/publicdomain/zero/1.0/"
    assert library.entries["test/seat/seat.obj"]["name"] == "Café chair"

    out = tmp_path / "out"
    build_dataset(out, sh3d.sh3d_objects("chair", cache=cache, table=table), TINY)
    (entry,) = load_index(out)
    assert entry.id == "sh3d-test-seat"
    assert entry.caption == "a red café chair"
    assert entry.extra["creator"] == "Jane Doe" and entry.extra["license"] == "CC0 public domain"
    assert entry.extra["texture"] == "color_only"
    # modelRotation turned the Z-up box Y-up; the Y-up to Z-up turn makes it stand tall again.
    extent = np.ptp(trimesh.load(out / entry.id / "mesh.ply").vertices, axis=0)
    assert extent.argmax() == 2
    assert (cache / "models" / "Test" / "test" / "seat" / "seat.mtl").is_file()


def test_properties_parser_follows_java_rules():
    text = b"a=1\n! bang comment\nkey\\ with\\ spaces : two\\\n   lines\nempty=\nx\\u0041=\\t\n"
    assert sh3d.parse_properties(text) == {"a": "1", "key with spaces": "twolines", "empty": "", "xA": "\t"}


def test_sh3d_category_list_matches_the_installed_package():
    try:
        furniture = sh3d.furniture_dir(download=False)
    except sh3d.Sh3dError as error:
        pytest.skip(f"sweethome3d-furniture is not in the cache ({error})")
    counts = {}
    libraries = {}
    for category in sh3d.CATEGORIES:
        rows = sh3d.category_rows(category)
        counts[category] = len(rows)
        for row in rows:
            if row.library not in libraries:
                libraries[row.library] = sh3d.Library.open(furniture / row.library)
            assert row.model in libraries[row.library].entries, row.model
    assert counts == {"chair": 65, "table": 49, "sofa": 24}


# ---------------------------------------------------------------------------------------------
# Command line


def test_data_command_line(tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="hypnerf")
    register(parser.add_subparsers(dest="command", required=True).add_parser("data"))
    args = parser.parse_args(
        ["data", "synth", "--out", str(tmp_path / "s"), "--objects", "1", "--views", "2", "--res", "8", "--seed", "1"]
    )
    assert args.func(args) == 0
    assert len(load_index(tmp_path / "s")) == 1
    args = parser.parse_args(["data", "import-meshes", "--out", str(tmp_path / "m"), "--category", "chair", "nope.obj"])
    assert args.func(args) == 1
    assert "not found" in capsys.readouterr().err
    args = parser.parse_args(["data", "import-sh3d", "--out", str(tmp_path / "h"), "--category", "sofa", "--limit", "2"])
    assert (args.category, args.limit, args.views, args.res) == ("sofa", 2, 91, 128)
    with pytest.raises(SystemExit):
        parser.parse_args(["data", "import-sh3d", "--out", "x", "--category", "lamp"])


def test_caption_files(tmp_path):
    (tmp_path / "c.json").write_text('{"a": "an apple chair"}')
    assert read_captions(tmp_path / "c.json") == {"a": "an apple chair"}
    (tmp_path / "c.tsv").write_text("a an apple chair\n")
    with pytest.raises(ValueError, match="stem<TAB>caption"):
        read_captions(tmp_path / "c.tsv")


# ---------------------------------------------------------------------------------------------
# Colour/material variants


def _textured_chair():
    rng = np.random.default_rng(0)
    for _ in range(50):
        spec = sample_spec(rng)
        mesh = chair_mesh(spec)
        if any(m.texture is not None for m in mesh.materials):
            return mesh
    raise AssertionError("the procedural generator made no textured chair in 50 tries")


def _mean_albedo_lab(mesh) -> np.ndarray:
    from skimage.color import rgb2lab

    return rgb2lab(mesh.mean_face_colours()[None, :, :3] / 255.0)[0].mean(axis=0)


def test_variants_are_deterministic_recolourings_of_the_same_geometry():
    from model.data.variants import material_variants

    mesh = _textured_chair()
    variants = material_variants(mesh, 4, "chair-a")
    again = material_variants(mesh, 4, "chair-a")
    assert len(variants) == 4 and variants[0] is mesh
    for a, b in zip(variants, again):
        assert all(np.array_equal(x.colour, y.colour) for x, y in zip(a.materials, b.materials))
    for variant in variants[1:]:
        assert np.array_equal(variant.vertices, mesh.vertices) and np.array_equal(variant.faces, mesh.faces)
    labs = [_mean_albedo_lab(v) for v in variants]
    for i in range(4):
        for j in range(i + 1, 4):
            assert np.linalg.norm(labs[i] - labs[j]) > 5.0, (i, j)
    other = material_variants(mesh, 4, "chair-b")
    assert not all(np.array_equal(x.colour, y.colour) for x, y in zip(other[1].materials, variants[1].materials))


def test_variants_keep_texture_patterns():
    from model.data.variants import material_variants

    mesh = _textured_chair()
    variant = material_variants(mesh, 2, "pattern")[1]
    luma = np.array([0.2126, 0.7152, 0.0722])
    for before, after in zip(mesh.materials, variant.materials):
        if before.texture is None:
            assert after.texture is None
            continue
        a, b = before.texture[..., :3] @ luma, after.texture[..., :3] @ luma
        if a.std() > 1e-3:
            assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.95
        assert 0.0 <= after.texture.min() and after.texture.max() <= 1.0


def test_variants_in_the_index_share_their_mesh_split(tmp_path):
    build_dataset(tmp_path, synth_objects(4, seed=2), RenderSettings(views=4, resolution=16, variants=3))
    entries = load_index(tmp_path)
    assert len(entries) == 12
    by_shape: dict[str, list] = {}
    for e in entries:
        by_shape.setdefault(e.extra["shape_id"], []).append(e)
        assert e.id == e.extra["shape_id"] or e.id == f"{e.extra['shape_id']}-v{e.extra['variant']}"
    assert len(by_shape) == 4
    for members in by_shape.values():
        assert sorted(m.extra["variant"] for m in members) == [0, 1, 2]
        assert len({m.split for m in members}) == 1
        assert len({m.caption for m in members}) >= 2  # captions follow the new colours
    assert set(e.split for e in entries) == set(OBJECT_SPLITS)
    mesh = trimesh.load(tmp_path / entries[0].id / "mesh.ply")
    variant = trimesh.load(tmp_path / by_shape[entries[0].extra["shape_id"]][1].id / "mesh.ply")
    assert np.allclose(mesh.vertices, variant.vertices)


def test_grouped_splits_match_ungrouped_splits_of_the_groups():
    ids = [f"obj-{i}" for i in range(20)]
    plain = assign_splits(ids)
    grouped = assign_splits([f"{i}-v1" for i in ids] + ids, groups={f"{i}-v1": i for i in ids})
    assert all(grouped[i] == plain[i] == grouped[f"{i}-v1"] for i in ids)


def test_variants_must_be_positive(capsys, tmp_path):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers().add_parser("data"))
    args = parser.parse_args(["data", "synth", "--out", str(tmp_path), "--objects", "1", "--variants", "0"])
    assert args.func(args) == 1
    assert "--variants must be at least 1" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# Shape augmentation


def test_height_stretch_is_continuous_and_fixes_the_cut():
    from model.data.augment import height_stretch

    z = np.array([-1.0, 0.2 - 1e-9, 0.2, 0.2 + 1e-9, 1.0])
    out = height_stretch(z, 0.2, lower=1.5, upper=0.5)
    assert out[2] == pytest.approx(0.2)
    assert out[1] == pytest.approx(out[3], abs=1e-8)  # no jump at the cut
    assert out[0] == pytest.approx(0.2 - 1.2 * 1.5) and out[4] == pytest.approx(0.2 + 0.8 * 0.5)
    assert np.all(np.diff(out) > 0)  # order (and so every face's connectivity) is kept


def test_deformed_copies_change_proportions_and_mirror_outward():
    from model.data.augment import Deformation, deformed

    mesh = normalise(chair_mesh(sample_spec(np.random.default_rng(0))))
    lo, hi = mesh.bounds()
    wide = deformed(mesh, Deformation(scale=(1.3, 1.0, 1.0), cut=0.5, lower=1.0, upper=1.0, mirror=False))
    extent, base = np.ptp(wide.bounds(), axis=0), hi - lo
    assert extent[0] / extent[2] == pytest.approx(1.3 * base[0] / base[2], rel=1e-6)
    legs = deformed(mesh, Deformation(scale=(1.0, 1.0, 1.0), cut=0.4, lower=1.4, upper=1.0, mirror=False))
    assert np.ptp(legs.bounds(), axis=0)[2] == pytest.approx(base[2] * (0.4 * 1.4 + 0.6), rel=1e-6)
    mirrored = deformed(mesh, Deformation(scale=(1.0, 1.0, 1.0), cut=0.5, lower=1.0, upper=1.0, mirror=True))
    assert np.allclose(np.sort(mirrored.vertices[:, 0]), np.sort(-(mesh.vertices[:, 0] - 0.5 * (lo[0] + hi[0]))))
    # a reflection flips winding back, so face normals still point out: the signed volume keeps its sign
    def volume(m):
        t = m.triangles
        return np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0

    assert np.sign(volume(mirrored)) == np.sign(volume(mesh)) and volume(mesh) != 0


def test_deformations_are_seeded_by_the_copy_id():
    from model.data.augment import AugmentRanges, draw_deformation

    a, b = draw_deformation("chair-aug1"), draw_deformation("chair-aug1")
    assert a == b and draw_deformation("chair-aug2") != a
    ranges = AugmentRanges()
    for k in range(20):
        d = draw_deformation(f"x-aug{k}")
        assert all(ranges.scale[0] <= s <= ranges.scale[1] for s in d.scale)
        assert ranges.cut[0] <= d.cut <= ranges.cut[1] and ranges.stretch[0] <= d.lower <= ranges.stretch[1]


def test_augmented_copies_only_of_train_meshes_and_in_their_split(tmp_path):
    build_dataset(tmp_path, synth_objects(8, seed=5), RenderSettings(views=4, resolution=16, variants=2, augment=2))
    entries = {e.id: e for e in load_index(tmp_path)}
    sources = [e for e in entries.values() if "augmented_from" not in e.extra]
    copies = [e for e in entries.values() if "augmented_from" in e.extra]
    plain = assign_splits({e.extra["shape_id"] for e in sources})
    assert {e.split for e in sources} == set(OBJECT_SPLITS)
    for e in sources:  # augmenting moves no source into another split
        assert e.split == plain[e.extra["shape_id"]]
    train_shapes = {e.extra["shape_id"] for e in sources if e.split == "train"}
    assert {c.extra["augmented_from"] for c in copies} == train_shapes
    assert len(copies) == len(train_shapes) * 2 * 2  # two copies, each in two colour variants
    for c in copies:
        assert c.split == "train"
        assert c.extra["shape_id"] != c.extra["augmented_from"]  # a new shape: its own shape code
        assert c.extra["shape_id"].startswith(c.extra["augmented_from"] + "-aug")
    some = copies[0]
    source_mesh = trimesh.load(tmp_path / some.extra["augmented_from"] / "mesh.ply")
    copy_mesh = trimesh.load(tmp_path / some.extra["shape_id"] / "mesh.ply")
    assert len(source_mesh.faces) == len(copy_mesh.faces) and not np.allclose(source_mesh.vertices, copy_mesh.vertices)


def test_augment_must_not_be_negative(capsys, tmp_path):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers().add_parser("data"))
    args = parser.parse_args(["data", "synth", "--out", str(tmp_path), "--objects", "1", "--augment", "-1"])
    assert args.func(args) == 1
    assert "--augment must be 0 or more" in capsys.readouterr().err
