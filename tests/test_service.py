"""The HTTP service against the real thing: ``hypnerf serve`` (uvicorn) in a subprocess with a tiny
bundle written by the real exporter, driven with httpx. Every endpoint; PNG, GIF, GLB, PLY and OBJ
files that parse; the cache (hit on the second creation, LRU eviction in memory and on disk under
tiny budgets, the disk cache surviving a restart); API keys; and every kind of bad input answered
4xx problem+json, never 500. Pieces with no HTTP path in a bundle without a query network (image
decoding, the compute pool's back-pressure, the catch-all handler) are tested in-process.
"""

from __future__ import annotations

import asyncio
import io
import json
import threading
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from model.bundle import export_bundle, load_bundle
from model.data.cameras import look_at, spherical_direction
from model.nerf.occupancy import OccupancyGrid
from model.nerf.scene import UNIT_BOX
from service.cache import NerfCache, NerfEntry, codes_nerf_id
from service.problems import PROBLEM_JSON, ProblemError
from service.process import ServiceServer
from service.settings import Settings
from service.uploads import decode_image

BODY_LIMIT = 50_000
KEY = "test-key-0123456789"


def first_view(chairs: Path, instance_id: str) -> np.ndarray:
    """An instance's first training image, RGBA floats ``[H, W, 4]``."""
    path = min((chairs / instance_id / "images").glob("*.png"))
    return np.asarray(Image.open(path).convert("RGBA"), dtype=np.float32) / 255.0


@pytest.fixture(scope="module")
def query_run(trained, chairs, tmp_path_factory) -> Path:
    """A query-network run for the tiny prior reading the real embedders, its MLP fitted in a few
    hundred steps to map each instance's first view to that instance's codes (its codes snap to
    codebook entries), with a bank of those views' embeddings."""
    from safetensors.torch import save_file

    from model.prior.embedders import TextEmbedder, embed_images, load_embedder
    from model.prior.io import load_prior
    from model.prior.query import (
        InputSlot,
        QueryConfig,
        QueryNetwork,
        code_distances,
        save_query,
    )

    prior = load_prior(trained[0])
    ids = [inst["id"] for inst in prior.instances]
    with torch.no_grad():
        shape_book, color_book = prior.net.codes(torch.arange(len(ids)))
    image = load_embedder("efficientnet-lite0")
    # an empty version skips the embedder-version check, so the text model loads only in the server
    slots = [InputSlot(image.name, ("image",), image.dim, 0, image.version()), InputSlot(TextEmbedder.name, ("text",), TextEmbedder.dim, image.dim, "")]
    torch.manual_seed(0)
    net = QueryNetwork(QueryConfig(hidden=32, layers=2, head="regression"), slots, shape_book.shape[1], color_book.shape[1], {"instances": ids})
    net.set_code_statistics(shape_book, color_book)
    views = torch.from_numpy(np.stack([first_view(chairs, i) for i in ids]))
    embeddings = embed_images(image, views)
    joint = net.joint(image=embeddings)
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-2)
    for _ in range(300):
        shape_d, color_d = code_distances(net, *net(joint), shape_book, color_book)
        loss = (shape_d.diagonal() + color_d.diagonal()).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    folder = tmp_path_factory.mktemp("query")
    save_query(folder, net.eval())
    save_file({"image": embeddings}, str(folder / "bank.safetensors"))
    return folder


@pytest.fixture(scope="module")
def service_bundle(trained, chairs, query_run, tmp_path_factory) -> Path:
    """The tiny prior with its query network, exported by the real exporter."""
    return export_bundle(trained[0], tmp_path_factory.mktemp("service") / "bundle", data=chairs, query=query_run)


@pytest.fixture(scope="module")
def plain_bundle(trained, chairs, tmp_path_factory) -> Path:
    """The tiny prior alone (no query network)."""
    return export_bundle(trained[0], tmp_path_factory.mktemp("service") / "plain", data=chairs)


@pytest.fixture(scope="module")
def server(service_bundle, tmp_path_factory):
    env = {"HYPNERF_LIMITS__MAX_BODY_BYTES": str(BODY_LIMIT), "HYPNERF_LIMITS__MAX_RENDER_SIDE": "96",
           "HYPNERF_LIMITS__MAX_MESH_RESOLUTION": "64", "HYPNERF_LIMITS__MAX_TURNTABLE_FRAMES": "8",
           "HYPNERF_LIMITS__MAX_IMAGE_PIXELS": "1000000"}
    with ServiceServer(service_bundle, tmp_path_factory.mktemp("state"), env=env) as running:
        yield running


@pytest.fixture(scope="module")
def client(server):
    with httpx.Client(base_url=server.url, timeout=60.0) as http:
        yield http


@pytest.fixture(scope="module")
def ids(client) -> list[str]:
    return [item["id"] for item in client.get("/v1/instances", params={"limit": 200}).json()["items"]]


@pytest.fixture(scope="module")
def nerf(client, ids) -> dict:
    return client.post("/v1/nerfs", json={"instance": ids[0]}).json()


def assert_problem(response: httpx.Response, status: int) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == PROBLEM_JSON
    body = response.json()
    assert body["status"] == status and body["title"] and "Traceback" not in response.text
    return body


# -- health, model, instances ---------------------------------------------------------------------


def test_health_readiness_and_model(client, service_bundle):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz").json()
    bundle = load_bundle(service_bundle)
    assert ready["status"] == "ready" and ready["bundle"] == bundle.digest
    info = client.get("/v1/model").json()
    assert info["bundle"]["digest"] == bundle.digest and info["bundle"]["format"] == bundle.manifest["format"]
    assert info["instances"] == len(bundle.instances) and info["codes"] == {"shape": 16, "color": 16}
    assert info["field"]["kind"] == "hashgrid" and info["scene_box"] == bundle.scene.to_aabb()
    assert info["limits"]["max_render_side"] == 96 and info["text_to_nerf"] is (bundle.query is not None)
    assert "/v1/nerfs/{nerf_id}/mesh" in client.get("/openapi.json").json()["paths"]


def test_instances_are_paginated_with_captions_and_attribution(client, ids, service_bundle):
    assert ids == [inst["id"] for inst in load_bundle(service_bundle).instances] and len(ids) == 6
    first = client.get("/v1/instances", params={"limit": 4}).json()
    assert first["total"] == 6 and [i["id"] for i in first["items"]] == ids[:4]
    following = client.get(first["next"]).json()
    assert following["offset"] == 4 and [i["id"] for i in following["items"]] == ids[4:] and following["next"] is None
    item = first["items"][0]
    assert item["caption"] and item["attribution"]["source"] == "synth" and item["shape_id"]
    assert client.get(f"/v1/instances/{ids[3]}").json()["index"] == 3


# -- NeRFs ----------------------------------------------------------------------------------------


def test_creation_is_content_addressed_and_cached(client, ids):
    before = client.get("/v1/cache").json()
    made = client.post("/v1/nerfs", json={"mix": {"shape": ids[0], "color": ids[5]}})
    assert made.status_code == 201 and made.json()["cached"] is False
    again = client.post("/v1/nerfs", json={"mix": {"shape": ids[0], "color": ids[5]}})
    assert again.status_code == 200 and again.json()["cached"] is True and again.json()["id"] == made.json()["id"]
    assert again.headers["location"] == f"/v1/nerfs/{made.json()['id']}"
    after = client.get("/v1/cache").json()
    assert after["memory_hits"] > before["memory_hits"] and after["memory_entries"] > before["memory_entries"]
    shown = client.get(f"/v1/nerfs/{made.json()['id']}").json()
    assert shown["source"] == {"mix": {"shape": ids[0], "color": ids[5]}} and shown["grid"]["resolution"] >= 8


def test_codes_interpolation_and_instances_name_the_same_nerfs(client, ids, nerf):
    codes = nerf["codes"]
    assert len(codes["shape"]) == 16 and len(codes["color"]) == 16
    assert client.post("/v1/nerfs", json={"codes": codes}).json()["id"] == nerf["id"]
    assert client.post("/v1/nerfs", json={"interpolate": {"a": ids[0], "b": ids[3], "t": 0.0}}).json()["id"] == nerf["id"]
    halfway = client.post("/v1/nerfs", json={"interpolate": {"a": ids[0], "b": ids[3]}}).json()
    assert halfway["id"] != nerf["id"] and halfway["source"]["interpolate"]["t"] == 0.5


def test_render_png_orbit_pose_and_transparency(client, nerf, server):
    url = f"/v1/nerfs/{nerf['id']}/render"
    png = client.get(url, params={"width": 48, "height": 32, "azimuth": 60, "elevation": 30, "radius": 2.0, "fov": 50})
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    image = Image.open(io.BytesIO(png.content))
    assert image.format == "PNG" and image.size == (48, 32) and image.mode == "RGB"
    assert np.asarray(image).std() > 1.0  # the chair is in view, not a blank image
    pose = look_at(2.0 * spherical_direction(30, 60))
    same = client.get(url, params={"width": 48, "height": 32, "fov": 50, "pose": ",".join(f"{v:.17g}" for v in pose.reshape(-1))})
    assert np.abs(np.asarray(Image.open(io.BytesIO(same.content)), dtype=int) - np.asarray(image, dtype=int)).max() <= 1
    clear = Image.open(io.BytesIO(client.get(url, params={"width": 32, "height": 32, "background": "transparent"}).content))
    alpha = np.asarray(clear)[..., 3]
    assert clear.mode == "RGBA" and alpha.min() < 10 and alpha.max() > 200
    black = np.asarray(Image.open(io.BytesIO(client.get(url, params={"width": 32, "height": 32, "background": "000000"}).content)))
    assert black[0, 0].max() < 10


def test_turntable_gif(client, nerf):
    gif = client.get(f"/v1/nerfs/{nerf['id']}/turntable", params={"frames": 4, "width": 24, "height": 24})
    assert gif.status_code == 200 and gif.headers["content-type"] == "image/gif"
    image = Image.open(io.BytesIO(gif.content))
    assert image.format == "GIF" and image.n_frames == 4 and image.size == (24, 24)


def _scene_mesh(data: bytes, file_type: str) -> trimesh.Trimesh:
    loaded = trimesh.load(io.BytesIO(data), file_type=file_type, process=False)
    return loaded.to_geometry() if isinstance(loaded, trimesh.Scene) else loaded


def test_meshes_parse_in_every_format_with_the_documented_up_axis(client, nerf):
    url = f"/v1/nerfs/{nerf['id']}/mesh"
    meshes = {}
    for fmt in ("glb", "ply", "obj"):
        response = client.get(url, params={"format": fmt, "resolution": 48})
        assert response.status_code == 200, response.text
        meshes[fmt] = _scene_mesh(response.content, fmt)
        assert len(meshes[fmt].faces) > 100 and meshes[fmt].visual.kind == "vertex"
    ply, glb = meshes["ply"], meshes["glb"]
    # GLB is Y-up: (x, y, z) -> (x, z, -y) of the Z-up world that PLY and OBJ keep
    assert np.allclose(glb.bounds[:, 1], ply.bounds[:, 2], atol=1e-4) and np.allclose(glb.bounds[:, 2], -ply.bounds[::-1, 1], atol=1e-4)
    assert np.allclose(meshes["obj"].bounds, ply.bounds, atol=1e-4)
    small = _scene_mesh(client.get(url, params={"format": "ply", "resolution": 48, "target_faces": 200}).content, "ply")
    assert len(small.faces) <= 220


def test_uv_texture_holds_the_colours_of_the_surface(client, nerf):
    url = f"/v1/nerfs/{nerf['id']}/mesh"
    vertex = _scene_mesh(client.get(url, params={"format": "ply", "resolution": 40}).content, "ply")
    response = client.get(url, params={"format": "glb", "resolution": 40, "texture": "uv", "texture_size": 256, "target_faces": 10**6})
    textured = _scene_mesh(response.content, "glb")
    assert textured.visual.kind == "texture" and textured.visual.material.baseColorTexture.size == (256, 256)
    sampled = trimesh.visual.uv_to_color(textured.visual.uv, textured.visual.material.baseColorTexture)[:, :3].astype(float)
    z_up = np.asarray(textured.vertices) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).T  # GLB's Y-up back to Z-up
    _, nearest = trimesh.proximity.ProximityQuery(vertex).vertex(z_up)
    expected = np.asarray(vertex.visual.vertex_colors)[nearest, :3].astype(float)
    assert np.abs(sampled - expected).mean() < 12.0
    archive = zipfile.ZipFile(io.BytesIO(client.get(url, params={"format": "obj", "resolution": 40, "texture": "uv", "texture_size": 128}).content))
    names = archive.namelist()
    assert "mesh.obj" in names and "material.mtl" in names and any(n.endswith(".png") for n in names)


def test_text_to_nerf_gives_a_nerf_of_codebook_codes_and_its_first_view(client, service_bundle):
    bundle = load_bundle(service_bundle)
    made = client.post("/v1/text-to-nerf", json={"text": "  a chair with four legs "})
    assert made.status_code in (200, 201), made.text
    nerf = made.json()["nerf"]
    # content addressed: codes an earlier request made already name that NeRF, with its first source
    assert nerf["id"] == codes_nerf_id(bundle.digest, np.asarray(nerf["codes"]["shape"], np.float32), np.asarray(nerf["codes"]["color"], np.float32))
    assert nerf["cached"] or nerf["source"] == {"text": "a chair with four legs"}
    # the query network's codes snap to codebook entries (shape and colour separately)
    assert np.isclose(bundle.shape_codes, nerf["codes"]["shape"], atol=1e-6).all(axis=1).any()
    assert np.isclose(bundle.color_codes, nerf["codes"]["color"], atol=1e-6).all(axis=1).any()
    png = client.get(made.json()["render_url"], params={"width": 32, "height": 32})
    assert png.status_code == 200 and Image.open(io.BytesIO(png.content)).size == (32, 32)
    assert client.post("/v1/text-to-nerf", json={"text": "a chair with four legs"}).json()["nerf"]["id"] == nerf["id"]
    assert made.json()["read_as"] == "a chair with four legs" and made.json()["colour_word"] is None


def test_text_to_nerf_reads_a_colour_name_as_its_palette_colour(client):
    crimson = client.post("/v1/text-to-nerf", json={"text": "an Crimson chair"}).json()
    assert crimson["read_as"] == "a red chair" and crimson["colour_word"] == {"name": "crimson", "palette": "red"}
    red = client.post("/v1/text-to-nerf", json={"text": "a red chair"}).json()
    assert red["read_as"] == "a red chair" and red["colour_word"] is None
    assert crimson["nerf"]["id"] == red["nerf"]["id"]  # the network read the same prompt


def test_retrieval_finds_the_instance_of_an_uploaded_view(client, chairs, ids):
    view = (first_view(chairs, ids[3]) * 255).round().astype(np.uint8)
    found = client.post("/v1/retrieve", files={"image": ("view.png", _encoded(Image.fromarray(view), "PNG"), "image/png")}, data={"k": "3"})
    assert found.status_code == 200, found.text
    matches = found.json()["matches"]
    assert len(matches) == 3 and matches[0]["instance"]["id"] == ids[3] and matches[0]["score"] > 0.9
    assert matches[0]["score"] >= matches[1]["score"] >= matches[2]["score"] and matches[0]["instance"]["caption"]
    jpeg = client.post("/v1/retrieve", files={"image": ("view.jpg", _encoded(Image.fromarray(view[..., :3]), "JPEG"), "image/jpeg")})
    assert jpeg.status_code == 200 and len(jpeg.json()["matches"]) == 5
    empty = np.zeros((16, 16, 4), dtype=np.uint8)  # fully transparent: no object to embed
    assert_problem(client.post("/v1/retrieve", files={"image": ("e.png", _encoded(Image.fromarray(empty), "PNG"), "image/png")}), 422)
    assert_problem(client.post("/v1/retrieve", files={"image": ("a.txt", b"plain text, not an image", "text/plain")}), 415)
    assert_problem(client.post("/v1/retrieve", files={"image": ("a.gif", _encoded(Image.new("RGB", (8, 8)), "GIF"), "image/gif")}), 415)
    assert_problem(client.post("/v1/retrieve", files={"image": ("b.png", _encoded(Image.new("RGB", (1200, 1000)), "PNG"), "image/png")}), 413)
    assert_problem(client.post("/v1/retrieve", files={"image": ("v.png", _encoded(Image.fromarray(view), "PNG"), "image/png")}, data={"k": "51"}), 422)


def test_metrics_by_route_template_and_cache(client, nerf):
    client.get(f"/v1/nerfs/{nerf['id']}/render", params={"width": 16, "height": 16})
    text = client.get("/metrics").text
    assert 'route="/v1/nerfs/{nerf_id}/render"' in text and nerf["id"] not in text
    assert 'hypnerf_cache_lookups_total{result="memory_hit"}' in text and 'hypnerf_cache_bytes{tier="disk"}' in text


# -- bad input -------------------------------------------------------------------------------------

NERF_ID = "f" * 64
POSE_OK = "1,0,0,0,0,1,0,0,0,0,1,2,0,0,0,1"


def _bad_requests(nerf_id: str, first: str) -> list[tuple[str, str, dict, int]]:
    render, mesh, turn = f"/v1/nerfs/{nerf_id}/render", f"/v1/nerfs/{nerf_id}/mesh", f"/v1/nerfs/{nerf_id}/turntable"
    return [
        ("GET", "/no/such/route", {}, 404),
        ("DELETE", "/v1/model", {}, 405),
        ("POST", "/v1/nerfs", {"content": b"{not json", "headers": {"content-type": "application/json"}}, 422),
        ("POST", "/v1/nerfs", {"json": {}}, 422),
        ("POST", "/v1/nerfs", {"json": [1, 2]}, 422),
        ("POST", "/v1/nerfs", {"json": {"instance": first, "mix": {"shape": first, "color": first}}}, 422),
        ("POST", "/v1/nerfs", {"json": {"instance": first, "extra": 1}}, 422),
        ("POST", "/v1/nerfs", {"json": {"instance": "no-such-instance"}}, 422),
        ("POST", "/v1/nerfs", {"json": {"mix": {"shape": first, "color": "no-such-instance"}}}, 422),
        ("POST", "/v1/nerfs", {"json": {"interpolate": {"a": first, "b": first, "t": 1.5}}}, 422),
        ("POST", "/v1/nerfs", {"content": b'{"codes": {"shape": [NaN], "color": [1]}}', "headers": {"content-type": "application/json"}}, 422),
        ("POST", "/v1/nerfs", {"content": b'{"codes": {"shape": [Infinity], "color": [1]}}', "headers": {"content-type": "application/json"}}, 422),
        ("POST", "/v1/nerfs", {"json": {"codes": {"shape": [0.0] * 15, "color": [0.0] * 16}}}, 422),
        ("POST", "/v1/nerfs", {"json": {"codes": {"shape": ["a"] * 16, "color": [0.0] * 16}}}, 422),
        ("POST", "/v1/nerfs", {"content": b"x" * (BODY_LIMIT + 1), "headers": {"content-type": "application/json"}}, 413),
        ("POST", "/v1/nerfs", {"content": iter([b"[" + b"0," * 20_000, b"0," * 20_000, b"0]"]), "headers": {"content-type": "application/json"}}, 413),
        ("POST", "/v1/nerfs", {"content": b"instance=x", "headers": {"content-type": "application/x-www-form-urlencoded"}}, 422),
        ("GET", "/v1/nerfs/not-an-id", {}, 422),
        ("GET", f"/v1/nerfs/{NERF_ID}", {}, 404),
        ("GET", f"/v1/nerfs/{NERF_ID}/render", {"params": {"width": 32, "height": 32}}, 404),
        ("GET", "/v1/instances/no-such-instance", {}, 404),
        ("GET", "/v1/instances", {"params": {"limit": 0}}, 422),
        ("GET", "/v1/instances", {"params": {"offset": -1}}, 422),
        ("GET", render, {"params": {"width": 97}}, 422),
        ("GET", render, {"params": {"height": 0}}, 422),
        ("GET", render, {"params": {"width": "wide"}}, 422),
        ("GET", render, {"params": {"azimuth": "nan"}}, 422),
        ("GET", render, {"params": {"elevation": 95}}, 422),
        ("GET", render, {"params": {"radius": 0.3}}, 422),
        ("GET", render, {"params": {"radius": -1}}, 422),
        ("GET", render, {"params": {"fov": 180}}, 422),
        ("GET", render, {"params": {"background": "#fff"}}, 422),
        ("GET", render, {"params": {"pose": "1,0,0"}}, 422),
        ("GET", render, {"params": {"pose": "a,b,c,d,e,f,g,h,i,j,k,l,m,n,o,p"}}, 422),
        ("GET", render, {"params": {"pose": POSE_OK.replace("1,0,0,0,0,1", "1,0,0,0,0,inf")}}, 422),
        ("GET", render, {"params": {"pose": POSE_OK.replace("1,0,0,0,0,1", "2,0,0,0,0,1")}}, 422),
        ("GET", render, {"params": {"pose": POSE_OK.replace("1,0,0,0,0,1", "-1,0,0,0,0,1")}}, 422),
        ("GET", render, {"params": {"pose": POSE_OK.replace(",2,", ",0,")}}, 422),
        ("GET", render, {"params": {"pose": POSE_OK[:-1] + "2"}}, 422),
        ("GET", turn, {"params": {"frames": 9}}, 422),
        ("GET", turn, {"params": {"format": "mp4"}}, 422),
        ("GET", turn, {"params": {"format": "avi"}}, 422),
        ("GET", turn, {"params": {"background": "transparent"}}, 422),
        ("GET", mesh, {"params": {"format": "stl"}}, 422),
        ("GET", mesh, {"params": {"resolution": 65}}, 422),
        ("GET", mesh, {"params": {"resolution": 2}}, 422),
        ("GET", mesh, {"params": {"target_faces": 1}}, 422),
        ("GET", mesh, {"params": {"format": "ply", "texture": "uv"}}, 422),
        ("GET", mesh, {"params": {"texture": "uv", "texture_size": 4096}}, 422),
        ("POST", "/v1/text-to-nerf", {"json": {"text": ""}}, 422),
        ("POST", "/v1/text-to-nerf", {"json": {"prompt": "a chair"}}, 422),
        ("POST", "/v1/retrieve", {"data": {"k": "0"}}, 422),
    ]


def test_every_bad_input_is_a_4xx_problem(client, nerf, ids):
    for method, path, kwargs, status in _bad_requests(nerf["id"], ids[0]):
        response = client.request(method, path, **kwargs)
        body = assert_problem(response, status)
        if status == 422 and path.startswith("/v1/nerfs") and "errors" in body:
            assert all(e["field"] is not None and e["message"] for e in body["errors"])
    invalid = client.get(f"/v1/nerfs/{nerf['id']}/render", params={"width": 97}).json()
    assert invalid["errors"][0]["field"] == "width" and "96" in invalid["errors"][0]["message"]
    nan = client.post("/v1/nerfs", content=b'{"codes": {"shape": [NaN], "color": [1]}}', headers={"content-type": "application/json"}).json()
    assert nan["errors"][0]["field"] == "codes.shape.0"
    assert client.delete("/v1/model").headers["allow"] == "GET"


# -- cache budgets, restart, keys -----------------------------------------------------------------


def _entry(seed: int, size: int = 1000) -> NerfEntry:
    params = {"tables": torch.randn(1, size, generator=torch.Generator().manual_seed(seed))}
    return NerfEntry(params, OccupancyGrid.full(UNIT_BOX, resolution=4), {"seed": seed})


def test_nerf_cache_is_a_byte_bounded_lru_in_memory_and_on_disk(tmp_path):
    size = _entry(0).nbytes
    cache = NerfCache(tmp_path, memory_bytes=2 * size, disk_bytes=3 * size + 3 * 1024)  # a file adds its header
    names = [codes_nerf_id("bundle", [float(i)], [0.0]) for i in range(5)]
    for i in range(3):
        cache.put(names[i], _entry(i))
    assert cache.get(names[0]) is not None  # from disk (evicted from memory), now most recent in memory
    cache.put(names[3], _entry(3))  # disk holds 3: the least recently used file (names[1]) goes
    stats = cache.stats()
    assert stats["memory_bytes"] <= 2 * size and stats["memory_entries"] == 2 and stats["disk_entries"] == 3
    assert cache.get(names[1]) is None and cache.get(names[2]) is not None
    assert stats["memory_evictions"] >= 2 and stats["disk_evictions"] == 1 and stats["disk_hits"] == 1
    reopened = NerfCache(tmp_path, memory_bytes=2 * size, disk_bytes=10 * size).get(names[3])
    assert reopened is not None and torch.equal(reopened.params["tables"], _entry(3).params["tables"]) and reopened.meta == {"seed": 3}
    (tmp_path / f"{names[2]}.safetensors").write_bytes(b"truncated")
    assert NerfCache(tmp_path, memory_bytes=0, disk_bytes=10 * size).get(names[2]) is None
    assert codes_nerf_id("b", [0.0, -0.0], [1.0]) == codes_nerf_id("b", [0.0, 0.0], [1.0]) != codes_nerf_id("c", [0.0, 0.0], [1.0])
    with pytest.raises(ValueError, match="64 lowercase hex"):
        cache.put("../escape", _entry(0))


def test_tiny_budgets_evict_and_the_disk_cache_survives_a_restart(plain_bundle, tmp_path):
    from service.resident import Resident

    # the sizes of one NeRF in memory and on disk, made the way the server makes them
    bundle = load_bundle(plain_bundle)
    probe = Resident(bundle, NerfCache(tmp_path / "probe", 1 << 30, 1 << 30), Settings(state_dir=tmp_path))
    first = bundle.instances[0]["id"]
    made_id, entry, _ = asyncio.run(probe.create(*probe.instance_codes(0), {"instance": first}))
    probe.close()
    file_bytes = (tmp_path / "probe" / f"{made_id}.safetensors").stat().st_size
    env = {"HYPNERF_CACHE_MEMORY_BYTES": str(int(1.5 * entry.nbytes)), "HYPNERF_CACHE_DISK_BYTES": str(int(2.5 * file_bytes)),
           "HYPNERF_API_KEYS": f"other-key,{KEY}"}
    server = ServiceServer(plain_bundle, tmp_path / "state", env=env)
    auth = {"Authorization": f"Bearer {KEY}"}
    with server, httpx.Client(base_url=server.url, timeout=60.0, headers=auth) as http:
        names = [item["id"] for item in http.get("/v1/instances").json()["items"][:3]]
        made = [http.post("/v1/nerfs", json={"instance": name}).json()["id"] for name in names]
        stats = http.get("/v1/cache").json()
        assert stats["memory_entries"] == 1 and stats["memory_evictions"] == 2
        assert stats["disk_entries"] == 2 and stats["disk_evictions"] == 1
        assert_problem(http.get(f"/v1/nerfs/{made[0]}"), 404)  # evicted from both tiers
        server.restart()
        assert http.get(f"/v1/nerfs/{made[2]}").status_code == 200 and http.get("/v1/cache").json()["disk_hits"] == 1
        again = http.post("/v1/nerfs", json={"instance": names[1]})
        assert again.status_code == 200 and again.json()["cached"] is True
        # keys: health stays open, everything else needs a configured bearer key
        assert httpx.get(server.url + "/readyz").status_code == 200
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {KEY}"}):
            body = assert_problem(httpx.get(server.url + "/v1/model", headers=headers), 401)
            assert "Bearer" in body["detail"]
        assert httpx.get(server.url + "/metrics", headers={"Authorization": "Bearer other-key"}).status_code == 200
        # without a query network, text-to-NeRF and retrieval say how to get one
        body = assert_problem(http.post("/v1/text-to-nerf", json={"text": "a red chair"}), 501)
        assert "no query network" in body["detail"] and "hypnerf export" in body["detail"]
        png = _encoded(Image.new("RGB", (8, 8)), "PNG")
        assert_problem(http.post("/v1/retrieve", files={"image": ("a.png", png, "image/png")}), 501)
        assert http.get("/v1/model").json()["text_to_nerf"] is False


def test_exposed_bind_needs_api_keys(monkeypatch, plain_bundle, tmp_path, caplog):
    from model.cli.main import main

    monkeypatch.delenv("HYPNERF_API_KEYS", raising=False)
    with pytest.raises(ValueError, match="HYPNERF_API_KEYS"):
        Settings(host="0.0.0.0")
    assert main(["serve", "--bundle", str(plain_bundle), "--host", "0.0.0.0"]) == 2 and "HYPNERF_API_KEYS" in caplog.text
    assert main(["serve", "--bundle", str(tmp_path)]) == 2 and "not a bundle" in caplog.text
    assert Settings(host="0.0.0.0", api_keys=["k"]).key_values() == [b"k"]
    monkeypatch.setenv("HYPNERF_API_KEYS", "a, b")
    monkeypatch.setenv("HYPNERF_LIMITS__MAX_RENDER_SIDE", "77")
    settings = Settings(host="::")
    assert settings.key_values() == [b"a", b"b"] and settings.limits.max_render_side == 77


# -- in-process pieces ------------------------------------------------------------------------------


def _encoded(image: Image.Image, fmt: str) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format=fmt)
    return buffer.getvalue()


def test_uploaded_images_are_checked_before_decoding():
    rgba = decode_image(_encoded(Image.new("RGB", (20, 10), (255, 0, 0)), "PNG"), max_pixels=1000)
    assert rgba.shape == (10, 20, 4) and rgba[0, 0].tolist() == [1.0, 0.0, 0.0, 1.0]
    assert decode_image(_encoded(Image.new("RGB", (8, 8)), "JPEG"), max_pixels=1000).shape == (8, 8, 4)
    cases = [(b"", 422), (b"GIF89a not an image we take", 415), (_encoded(Image.new("RGB", (8, 8)), "GIF"), 415),
             (_encoded(Image.new("RGB", (8, 8)), "BMP"), 415), (_encoded(Image.new("RGB", (50, 50)), "PNG"), 413),
             (_encoded(Image.new("RGB", (30, 30)), "PNG")[:60], 422)]
    for data, status in cases:
        with pytest.raises(ProblemError) as caught:
            decode_image(data, max_pixels=1000)
        assert caught.value.status == status, (data[:12], caught.value.detail)


def test_a_full_compute_pool_answers_429_with_retry_after(plain_bundle, tmp_path):
    from service.resident import Resident

    settings = Settings(state_dir=tmp_path, limits={"max_pending_renders": 1}, render_workers=1)
    resident = Resident(load_bundle(plain_bundle), NerfCache(tmp_path, 0, 0), settings)
    release = threading.Event()

    async def scenario():
        busy = asyncio.ensure_future(resident.compute("render", release.wait))
        await asyncio.sleep(0.05)
        with pytest.raises(ProblemError) as caught:
            await resident.compute("render", lambda: None)
        release.set()
        await busy
        return caught.value

    refused = asyncio.run(scenario())
    resident.close()
    assert refused.status == 429 and refused.headers["Retry-After"] == "1"


def test_a_nerf_without_a_surface_is_a_clear_422_for_meshes(plain_bundle, tmp_path):
    from service.resident import Resident
    from service.routers.nerfs import build_mesh
    from service.schemas.nerfs import MeshQuery

    bundle = load_bundle(plain_bundle)
    resident = Resident(bundle, NerfCache(tmp_path, 0, 0), Settings(state_dir=tmp_path))
    empty = OccupancyGrid(torch.zeros(8, 8, 8, dtype=torch.bool), *bundle.scene.tensors())
    with pytest.raises(ProblemError) as caught:
        build_mesh(resident, NerfEntry(bundle.generate(*resident.instance_codes(0)), empty), MeshQuery(resolution=16))
    resident.close()
    assert caught.value.status == 422 and "no surface" in caught.value.detail


def test_an_unexpected_error_is_a_generic_500_problem_without_the_traceback(tmp_path):
    from service.app import create_app

    app = create_app(Settings(state_dir=tmp_path))

    async def broken():
        raise RuntimeError("secret internals")

    app.add_api_route("/broken", broken)

    async def call():
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as http:
            return await http.get("/broken")

    response = asyncio.run(call())
    body = assert_problem(response, 500)
    assert "secret" not in response.text and body["error_id"] in body["detail"] and json.loads(response.text)["type"].endswith("internal")
