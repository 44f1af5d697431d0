"""Bundles: export of the tiny prior, ONNX-vs-torch parity, each weight stored once, verified
loading that refuses tampered, truncated, missing and newer-format bundles, and the CLI."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

import model.bundle.query as bundle_query
from model.bundle import BUNDLE_FORMAT, BundleError, export_bundle, load_bundle
from model.bundle.manifest import file_digest
from model.bundle.onnx_export import safetensors_spans
from model.bundle.parity import parity, query_parity
from model.cli.main import main
from model.prior.io import load_prior
from model.prior.query import (
    InputSlot,
    QueryConfig,
    QueryNetwork,
    colour_wearers,
    load_query,
    nearest_instances,
    save_query,
    snap_codes,
)

PARITY_TOLERANCE = 1e-4
IMAGE_DIM, TEXT_DIM = 8, 6


@pytest.fixture(scope="module")
def bundle_dir(trained, chairs, tmp_path_factory) -> Path:
    run, _ = trained
    return export_bundle(run, tmp_path_factory.mktemp("bundles") / "tiny", data=chairs)


def _query_folder(run: Path, folder: Path, head: str = "regression") -> Path:
    """A query-network run of the tiny prior as `hypnerf train-query` lays it out (untrained weights, small embedding slots)."""
    prior = load_prior(run)
    ids = [inst["id"] for inst in prior.instances]
    with torch.no_grad():
        shape_book, color_book = prior.net.codes(torch.arange(len(ids)))
    slots = [InputSlot("efficientnet-lite0", ("image",), IMAGE_DIM, 0, "image-v1"), InputSlot("minilm", ("text",), TEXT_DIM, IMAGE_DIM, "text-v1")]
    torch.manual_seed(0)
    net = QueryNetwork(QueryConfig(hidden=32, layers=2, head=head), slots, shape_book.shape[1], color_book.shape[1],
                       {"embedders": ["efficientnet-lite0", "minilm"], "instances": ids}, (prior.net.shape_codes.num_embeddings, len(ids)))
    net.set_code_statistics(prior.net.shape_codes.weight.detach() if head != "regression" else shape_book, color_book)
    save_query(folder, net.eval())
    save_file({"image": F.normalize(torch.randn(len(ids), IMAGE_DIM), dim=-1)}, str(folder / "bank.safetensors"))
    return folder


@pytest.fixture(scope="module")
def query_run(trained, tmp_path_factory) -> Path:
    run, _ = trained
    return _query_folder(run, tmp_path_factory.mktemp("query"))


@pytest.fixture(scope="module")
def full_bundle(trained, chairs, query_run, tmp_path_factory) -> Path:
    """A bundle with every component, exported through the command line."""
    run, _ = trained
    root = tmp_path_factory.mktemp("full")
    denoiser = root / "denoiser"
    denoiser.mkdir()
    save_file({"encoder.weight": torch.ones(4, 4)}, str(denoiser / "denoiser.safetensors"))
    (denoiser / "denoiser.json").write_text(json.dumps({"format": 1}))
    out = root / "bundle"
    args = ["export", "--run", str(run), "--out", str(out), "--data", str(chairs), "--query", str(query_run), "--denoiser", str(denoiser)]
    assert main(args) == 0
    return out


@pytest.fixture
def bundle_copy(bundle_dir, tmp_path) -> Path:
    return Path(shutil.copytree(bundle_dir, tmp_path / "copy"))


def test_manifest_lists_every_file_once_with_its_hash(bundle_dir):
    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    assert manifest["format"] == BUNDLE_FORMAT
    assert manifest["components"] == ["hypernet"]
    on_disk = sorted(p.name for p in bundle_dir.iterdir() if p.name != "manifest.json")
    assert on_disk == sorted(manifest["files"]) == ["hypernet.onnx", "instances.json", "weights.safetensors"]
    for name, record in manifest["files"].items():
        assert record == {"sha256": file_digest(bundle_dir / name), "bytes": (bundle_dir / name).stat().st_size}
    assert set(manifest["configs"]) >= {"hypernet", "field", "scene_box", "camera"}
    assert load_bundle(bundle_dir).digest == hashlib.sha256((bundle_dir / "manifest.json").read_bytes()).hexdigest()


@pytest.mark.parametrize("graph, weights", [("hypernet.onnx", "weights.safetensors"), ("query.onnx", "query.safetensors")])
def test_each_weight_is_stored_once(full_bundle, graph, weights):
    model = onnx.load(str(full_bundle / graph), load_external_data=False)
    external = [t for t in model.graph.initializer if t.data_location == onnx.TensorProto.EXTERNAL]
    embedded = [t for t in model.graph.initializer if t.data_location != onnx.TensorProto.EXTERNAL]
    assert external and all({e.key: e.value for e in t.external_data}["location"] == weights for t in external)
    assert sum(int(np.prod(t.dims)) for t in embedded) < 64  # only reshape targets and scalars stay in the graph
    # a window of the largest weight, in its stored precision and widened to float32, is found only in the weights file
    spans = safetensors_spans(full_bundle / weights)
    largest = max(spans, key=lambda name: spans[name].length)
    stored = load_file(str(full_bundle / weights))[largest].reshape(-1)[100:132]
    windows = [stored.numpy().tobytes(), stored.float().numpy().tobytes()]
    holders = {p.name for p in full_bundle.iterdir() for w in windows if w in p.read_bytes()}
    assert holders == {weights}
    assert (full_bundle / graph).stat().st_size < (full_bundle / weights).stat().st_size


def test_onnx_matches_torch_on_parameters_and_render(bundle_dir):
    bundle = load_bundle(bundle_dir, threads=1)
    last = len(bundle.instances) - 1
    codes = [
        (bundle.shape_codes[0], bundle.color_codes[0]),
        (bundle.shape_codes[0], bundle.color_codes[last]),  # a shape/colour mix
        (0.5 * (bundle.shape_codes[0] + bundle.shape_codes[last]), 0.5 * (bundle.color_codes[0] + bundle.color_codes[last])),
    ]
    for shape, color in codes:
        result = parity(bundle, shape, color)
        assert result["params_max_abs_diff"] <= PARITY_TOLERANCE
        assert result["image_max_abs_diff"] <= PARITY_TOLERANCE
        assert result["coverage"] > 0.02  # the render shows the object, not just background
    params = bundle.generate(bundle.shape_codes[0], bundle.color_codes[0][None])
    expected = bundle.field.param_shapes()
    assert {name: tuple(value.shape) for name, value in params.items()} == {name: (1, *shape) for name, shape in expected.items()}
    assert all(value.dtype == torch.float32 and bool(torch.isfinite(value).all()) for value in params.values())


def test_codes_instances_and_torch_hypernetwork(bundle_dir, trained):
    run, _ = trained
    prior = load_prior(run)
    bundle = load_bundle(bundle_dir)
    assert [inst["id"] for inst in bundle.instances] == [inst["id"] for inst in prior.instances]
    shape, color = prior.net.codes(torch.arange(len(prior.instances)))
    np.testing.assert_array_equal(bundle.shape_codes, shape.detach().numpy())
    np.testing.assert_array_equal(bundle.color_codes, color.detach().numpy())
    net = bundle.hypernet()
    assert net is bundle.hypernet() and not net.training
    assert all(p.dtype == torch.float32 and not p.requires_grad for p in net.parameters())
    for key, value in prior.net.state_dict().items():
        assert torch.equal(net.state_dict()[key], value)
    target = bundle.instances[-1]["id"]
    assert bundle.instance_index(target) == len(bundle.instances) - 1
    with pytest.raises(ValueError, match="not an instance"):
        bundle.instance_index("no-such-chair")
    assert bundle.camera.width == bundle.camera.height == 32
    assert bundle.scene == prior.scene and bundle.query is None and bundle.denoiser_path is None


def test_generate_rejects_bad_codes(bundle_dir):
    bundle = load_bundle(bundle_dir, verify=False)
    shape, color = bundle.shape_codes[0], bundle.color_codes[0]
    with pytest.raises(ValueError, match="shape code has 16 numbers"):
        bundle.generate(shape[:-1], color)
    with pytest.raises(ValueError, match="finite"):
        bundle.generate(shape, np.full_like(color, np.nan))
    with pytest.raises(ValueError, match="colour code"):
        bundle.generate(shape, np.stack([color, color]))


def test_attribution_comes_from_the_dataset_index(bundle_dir, chairs):
    bundle = load_bundle(bundle_dir)
    index = {o["id"]: o for o in json.loads((chairs / "index.json").read_text())["objects"]}
    records = bundle.manifest["attribution"]
    assert [r["id"] for r in records] == [inst["id"] for inst in bundle.instances]
    for inst in bundle.instances:
        record = inst["attribution"]
        assert set(record) >= {"id", "name", "creator", "licence", "source"}
        assert record["id"] == inst["id"] and record["source"] == index[inst["id"]]["source"] == "synth"
        assert (record["changes"] is None) == (index[inst["id"]].get("variant", 0) == 0)


def test_a_tampered_byte_is_refused(bundle_copy):
    path = bundle_copy / "weights.safetensors"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(BundleError, match=r"weights\.safetensors does not match its sha256.*re-export"):
        load_bundle(bundle_copy)


def test_a_truncated_file_is_refused(bundle_copy):
    path = bundle_copy / "hypernet.onnx"
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(BundleError, match=r"hypernet\.onnx has \d+ bytes but the manifest records"):
        load_bundle(bundle_copy, verify=False)


def test_a_missing_file_is_refused(bundle_copy):
    (bundle_copy / "instances.json").unlink()
    with pytest.raises(BundleError, match=r"instances\.json is missing.*download it again"):
        load_bundle(bundle_copy)
    (bundle_copy / "manifest.json").unlink()
    with pytest.raises(BundleError, match=r"manifest\.json is missing"):
        load_bundle(bundle_copy)


def test_a_newer_format_is_refused_with_the_version_it_needs(bundle_copy):
    manifest = json.loads((bundle_copy / "manifest.json").read_text())
    manifest["format"] = BUNDLE_FORMAT + 1
    (bundle_copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match=rf"format-{BUNDLE_FORMAT + 1} bundle.*up to {BUNDLE_FORMAT}.*reads format {BUNDLE_FORMAT + 1}"):
        load_bundle(bundle_copy)


def test_export_refuses_a_folder_that_is_not_a_bundle(trained, chairs, tmp_path):
    run, _ = trained
    (tmp_path / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="is not a bundle"):
        export_bundle(run, tmp_path, data=chairs)
    with pytest.raises(FileNotFoundError, match="pass --data"):
        export_bundle(run, tmp_path / "b", data=tmp_path)
    assert (tmp_path / "notes.txt").read_text() == "keep me" and not (tmp_path / "b").exists()


def test_cli_export_with_every_component_and_verify_round_trip(full_bundle, trained, chairs, tmp_path, capsys, caplog):
    assert main(["export", "--verify", str(full_bundle)]) == 0
    printed = capsys.readouterr().out
    assert "verified 9 files" in printed and "components: hypernet, query, denoiser" in printed and "render max |diff|" in printed
    assert "query network: reads efficientnet-lite0 (image), minilm (text)" in printed
    bundle = load_bundle(full_bundle)
    assert sorted(p.name for p in full_bundle.iterdir() if p.name != "manifest.json") == sorted(bundle.manifest["files"])
    assert bundle.denoiser_path == full_bundle / "denoiser.safetensors" and bundle.query is not None
    assert not any(p.name.startswith(".") for p in full_bundle.parent.iterdir())  # no staging folder left behind
    damaged = shutil.copytree(full_bundle, tmp_path / "damaged")
    (damaged / "denoiser.json").write_text("{}")
    assert main(["export", "--verify", str(damaged)]) == 2
    assert "denoiser.json has 2 bytes" in caplog.text
    # exporting over an earlier bundle replaces it whole: no file of its optional parts is left
    run, _ = trained
    assert main(["export", "--run", str(run), "--out", str(damaged), "--data", str(chairs)]) == 0
    assert load_bundle(damaged).manifest["components"] == ["hypernet"]
    assert sorted(p.name for p in damaged.iterdir()) == ["hypernet.onnx", "instances.json", "manifest.json", "weights.safetensors"]


def test_query_network_in_onnx_matches_torch(full_bundle, query_run):
    bundle = load_bundle(full_bundle, threads=1)
    query = bundle.query
    torch_net = load_query(full_bundle)  # the bundle folder is also a query run: its weights are stored once
    reference = load_query(query_run)
    assert all(torch.equal(a, b) for a, b in zip(torch_net.state_dict().values(), reference.state_dict().values(), strict=True))
    embeddings = torch.randn(5, query.input_dim)
    with torch.no_grad():
        shape, color = torch_net(embeddings)
        snapped = snap_codes(torch_net, shape, color, torch.from_numpy(bundle.shape_codes), torch.from_numpy(bundle.color_codes))
    for row in range(5):
        raw = query.codes(embeddings[row].numpy(), snap=False)
        assert np.abs(raw[0] - shape[row].numpy()).max() <= PARITY_TOLERANCE
        assert np.abs(raw[1] - color[row].numpy()).max() <= PARITY_TOLERANCE
        codes = query.codes(embeddings[row].numpy())
        np.testing.assert_array_equal(codes[0], snapped[0][row].numpy())
        np.testing.assert_array_equal(codes[1], snapped[1][row].numpy())
    image = np.zeros(query.input_dim, np.float32)
    image[:IMAGE_DIM] = np.random.default_rng(0).normal(size=IMAGE_DIM)
    rows, scores = query.retrieve(image, k=3)
    with torch.no_grad():
        shape, color = torch_net(torch.from_numpy(image)[None])
    expected_rows = nearest_instances(torch_net, shape, color, torch.from_numpy(bundle.shape_codes), torch.from_numpy(bundle.color_codes), k=3)[0]
    np.testing.assert_array_equal(rows, expected_rows.numpy())
    assert np.all(np.diff(scores) <= 0) and np.all((scores > 0) & (scores <= 1))
    assert bundle.manifest["configs"]["query"]["retrieval"]["instances"] == [inst["id"] for inst in bundle.instances]
    assert query_parity(bundle) <= PARITY_TOLERANCE
    with pytest.raises(ValueError, match="has none"):
        query.retrieve(np.ones(query.input_dim, np.float32) * np.r_[np.zeros(IMAGE_DIM), np.ones(TEXT_DIM)], k=3)
    with pytest.raises(ValueError, match=f"{query.input_dim} finite numbers"):
        query.codes(np.zeros(3))


@pytest.mark.parametrize("head", ["shape-codebook", "codebook"])
def test_codebook_heads_export_with_each_weight_once_and_match_torch(trained, chairs, tmp_path, head):
    run, _ = trained
    folder = _query_folder(run, tmp_path / "query", head)
    bundle = load_bundle(export_bundle(run, tmp_path / "bundle", data=chairs, query=folder), threads=1)
    torch_net = load_query(folder)
    embeddings = torch.randn(4, bundle.query.input_dim)
    with torch.no_grad():
        shape, color = torch_net(embeddings)
    for row in range(4):
        raw = bundle.query.codes(embeddings[row].numpy(), snap=False)
        assert np.abs(raw[0] - shape[row].numpy()).max() <= PARITY_TOLERANCE
        assert np.abs(raw[1] - color[row].numpy()).max() <= PARITY_TOLERANCE
        assert any(np.array_equal(raw[0], code) for code in bundle.shape_codes)  # the shape is a codebook entry
    assert query_parity(bundle) <= PARITY_TOLERANCE


class _Embedder:
    """A stand-in for a packaged embedder: a fixed embedding per call, and a version."""

    def __init__(self, name: str, dim: int, version: str):
        self.name, self.dim, self.version_text = name, dim, version

    def version(self) -> str:
        return self.version_text

    def embed(self, inputs) -> torch.Tensor:
        return torch.arange(1, self.dim + 1, dtype=torch.float32)[None].expand(len(inputs), -1)


def test_query_embeds_into_its_slots_and_refuses_another_embedder_version(full_bundle, monkeypatch):
    versions = {"minilm": "text-v1", "efficientnet-lite0": "image-v2"}
    dims = {"minilm": TEXT_DIM, "efficientnet-lite0": IMAGE_DIM}
    monkeypatch.setattr(bundle_query, "load_embedder", lambda name: _Embedder(name, dims[name], versions[name]))
    query = load_bundle(full_bundle).query
    joint = query.embed_text("a red chair")
    np.testing.assert_array_equal(joint, np.r_[np.zeros(IMAGE_DIM), np.arange(1, TEXT_DIM + 1)].astype(np.float32))
    shape, color = query.codes(joint)
    assert shape.shape == (16,) and color.shape == (16,) and np.isfinite(shape).all()
    # the colour a prompt names restricts the snapped colour code to the instances wearing it
    bundle = load_bundle(full_bundle)
    # the export measured each instance's colours in renders of its own codes
    assert query.rendered_colours is not None and len(query.rendered_colours) == len(bundle.instances)
    assert [inst["rendered_colours"] for inst in bundle.instances] == query.rendered_colours
    for colour in {c for c in query.instance_colours if c}:
        wearers = colour_wearers(query.instance_colours, colour, query.rendered_colours)
        _, worn = query.codes(joint, colour=colour)
        assert any(np.array_equal(worn, bundle.color_codes[n]) for n in wearers)
        assert query.text_codes(f"a {colour} chair")[2].palette == colour
    assert len({c for c in query.instance_colours if c}) >= 2
    with pytest.raises(BundleError, match="efficientnet-lite0 embedder is version image-v2.*trained on version image-v1"):
        query.embed_image(np.ones((8, 8, 4), np.float32))


def test_rendered_colours_of_an_older_bundle_are_optional_and_bad_ones_are_refused():
    from model.bundle.load import _rendered_colours

    assert _rendered_colours([{"id": "a"}, {"id": "b"}]) is None
    shares = [{"red": 0.7, "grey": 0.3}, {}]
    assert _rendered_colours([{"rendered_colours": s} for s in shares]) == shares
    with pytest.raises(BundleError, match="rendered_colours.*re-export"):
        _rendered_colours([{"rendered_colours": {"red": 0.7}}, {"id": "b"}])
    with pytest.raises(BundleError, match="rendered_colours"):
        _rendered_colours([{"rendered_colours": {"red": "most"}}])
