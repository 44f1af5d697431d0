"""Multi-resolution hash encoding: semantics, the fused CPU kernel against the PyTorch reference."""

from __future__ import annotations

import json
import math
import os
import shutil
import time

import pytest
import torch

from model.nerf import config
from model.nerf.encodings import kernels
from model.nerf.encodings.hashgrid import PRIMES, HashGridConfig, encode, encode_reference, init_tables, uses_kernel

PAPER = HashGridConfig()
# Levels 0-2 dense ((res+1)^3 <= 4096), the rest hashed.
MIXED = HashGridConfig(levels=6, log2_table_size=12, features=2, base_resolution=2, finest_resolution=300)
WIDE = HashGridConfig(levels=4, log2_table_size=14, features=4, base_resolution=4, finest_resolution=64)
NARROW = HashGridConfig(levels=3, log2_table_size=10, features=1, base_resolution=3, finest_resolution=50)


@pytest.fixture(scope="module")
def kernel():
    """The compiled kernel; a build failure fails the tests, only a missing compiler skips them."""
    if shutil.which(os.environ.get("CXX", "c++")) is None:
        pytest.skip("no C++ compiler on this machine")
    return kernels.hashgrid_ops()


@pytest.fixture(autouse=True)
def _no_forced_reference(monkeypatch):
    monkeypatch.delenv("HYPNERF_PURE_TORCH", raising=False)


def _random_tables(cfg: HashGridConfig, batch: int, dtype=torch.float32, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand((batch, *cfg.table_shape), generator=g, dtype=dtype) * 2 - 1).requires_grad_()


def _awkward_points(cfg: HashGridConfig, batch: int, n: int, dtype=torch.float32, seed: int = 1) -> torch.Tensor:
    """Random points plus the awkward ones: 0, 1, every level's cell borders, points outside [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand((batch, n, 3), generator=g, dtype=dtype)
    special = [0.0, 1.0, -0.25, 1.5, 0.5]
    for res in cfg.resolutions:
        special += [k / res for k in (1, res // 2, res - 1)]
    s = torch.tensor(special, dtype=dtype)
    m = min(len(s), n)
    pts[:, :m, 0] = s[:m]
    pts[:, :m, 1] = s.flip(0)[:m]
    pts[:, :m, 2] = s.roll(3)[:m]
    return pts.requires_grad_()


def _impl(request, name):
    """``encode`` (requiring the compiled kernel) or the reference, by parameter name."""
    if name == "kernel":
        request.getfixturevalue("kernel")
        return encode
    return encode_reference


def _grads(fn, points, tables, cfg, upstream):
    out = fn(points, tables, cfg)
    grad_points, grad_tables = torch.autograd.grad(out, (points, tables), upstream)
    return out, grad_points, grad_tables


def _close(actual, expected, rtol):
    """Max error relative to the expected tensor's scale (sums of many terms round differently)."""
    scale = expected.abs().max().clamp_min(1e-12)
    torch.testing.assert_close(actual, expected, rtol=0, atol=rtol * scale.item())


# ----------------------------------------------------------------------------- configuration


def test_config_json_roundtrip_and_shapes():
    cfg = HashGridConfig(levels=8, log2_table_size=12, features=4, base_resolution=8, finest_resolution=512)
    restored = config.from_dict(HashGridConfig, json.loads(json.dumps(config.to_dict(cfg))))
    assert restored == cfg
    assert cfg.output_dim == 32
    assert cfg.table_shape == (8, 4096, 4)
    assert PAPER.table_shape == (16, 2048, 2) and PAPER.output_dim == 32


def test_resolutions_follow_geometric_series():
    cfg = PAPER
    b = math.exp((math.log(2048) - math.log(16)) / 15)
    assert cfg.per_level_scale == pytest.approx(b)
    assert cfg.resolutions[0] == 16 and cfg.resolutions[-1] == 2048
    assert list(cfg.resolutions) == [math.floor(16 * b**level + 1e-9) for level in range(16)]
    for levels in range(2, 20):
        r = HashGridConfig(levels=levels, base_resolution=16, finest_resolution=4096).resolutions
        assert r[0] == 16 and r[-1] == 4096 and list(r) == sorted(r)


def test_dense_rule():
    assert MIXED.dense == tuple((r + 1) ** 3 <= 4096 for r in MIXED.resolutions)
    assert MIXED.dense[:3] == (True, True, True) and not any(MIXED.dense[3:])
    assert not any(PAPER.dense)  # 17^3 > 2^11 already at the coarsest level


@pytest.mark.parametrize(
    "bad",
    [dict(levels=0), dict(features=0), dict(log2_table_size=25), dict(base_resolution=64, finest_resolution=32),
     dict(levels=1, base_resolution=16, finest_resolution=32), dict(finest_resolution=2**20)],
)
def test_config_rejects_invalid(bad):
    with pytest.raises(ValueError):
        HashGridConfig(**bad)


def test_init_tables_small_uniform_and_seeded():
    t = init_tables(PAPER, 3, generator=torch.Generator().manual_seed(5))
    assert t.shape == (3, 16, 2048, 2) and t.dtype == torch.float32
    assert t.abs().max() <= 1e-4 and t.std() > 1e-5
    assert torch.equal(t, init_tables(PAPER, 3, generator=torch.Generator().manual_seed(5)))


# ----------------------------------------------------------------------------- golden values


@pytest.mark.parametrize("impl", ["kernel", "reference"])
def test_golden_dense_level(impl, request):
    """res = 2: 27 vertices stored densely at row x + 3y + 9z; table holds (row, row^2)."""
    cfg = HashGridConfig(levels=1, log2_table_size=5, features=2, base_resolution=2, finest_resolution=2)
    assert cfg.dense == (True,)
    rows = torch.arange(32, dtype=torch.float32)
    tables = torch.stack([rows, rows**2], dim=-1).view(1, 1, 32, 2)
    # pos = (0.5, 1.0, 1.5): cell (0, 1, 1), fractions (0.5, 0, 0.5): corners 12, 13, 21, 22 at 1/4.
    points = torch.tensor([[[0.25, 0.5, 0.75]]])
    fn = _impl(request, impl)
    out = fn(points, tables, cfg)
    assert out.tolist() == [[[17.0, (144 + 169 + 441 + 484) / 4]]]


@pytest.mark.parametrize("impl", ["kernel", "reference"])
def test_linear_table_gives_exact_values_and_point_gradients(impl, request):
    """Vertex values a.v interpolate to res * a.p everywhere, so d out / d p = res * a (also at x = 1)."""
    res = 4
    cfg = HashGridConfig(levels=1, log2_table_size=7, features=2, base_resolution=res, finest_resolution=res)
    assert cfg.dense == (True,)
    a = torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.0, 5.0]])  # one linear function per feature
    v = torch.arange(res + 1, dtype=torch.float32)
    vz, vy, vx = torch.meshgrid(v, v, v, indexing="ij")  # row = x + 5y + 25z
    vertices = torch.stack([vx, vy, vz], dim=-1).reshape(-1, 3)
    tables = torch.zeros(1, 1, 128, 2)
    tables[0, 0, : (res + 1) ** 3] = vertices @ a.T
    points = torch.tensor([[[0.3, 0.7, 0.1], [1.0, 1.0, 1.0], [0.0, 0.5, 0.25], [0.75, 0.0, 1.0]]], requires_grad=True)
    fn = _impl(request, impl)
    out = fn(points, tables, cfg)
    torch.testing.assert_close(out, res * points.detach() @ a.T, rtol=1e-6, atol=1e-5)
    (grad,) = torch.autograd.grad(out.sum(), points)
    torch.testing.assert_close(grad, (res * a.sum(0)).expand(1, 4, 3))


@pytest.mark.parametrize("impl", ["kernel", "reference"])
def test_hashed_level_matches_python_integer_hash(impl, request):
    """Vertices so large that y * 2654435761 overflows int32; rows recomputed with Python ints."""
    res, t = 2048, 2**11
    cfg = HashGridConfig(levels=1, log2_table_size=11, features=2, base_resolution=res, finest_resolution=res)
    assert cfg.dense == (False,)
    tables = _random_tables(cfg, 1).detach()
    cells = [(1001, 1777, 1999), (0, 2047, 5), (2047, 2047, 2047)]
    # Cell centres: every corner weighs 1/8 (exact in float32 since res is a power of two).
    points = torch.tensor([[[(c + 0.5) / res for c in cell] for cell in cells]])
    fn = _impl(request, impl)
    out = fn(points, tables, cfg)[0].double()
    for i, (x, y, z) in enumerate(cells):
        rows = []
        for c in range(8):
            vx, vy, vz = x + (c & 1), y + (c >> 1 & 1), z + (c >> 2 & 1)
            assert vy * PRIMES[1] > 2**31  # the product does not fit int32
            rows.append((vx * PRIMES[0] ^ vy * PRIMES[1] ^ vz * PRIMES[2]) % t)
        expected = tables[0, 0, rows].double().mean(dim=0)
        torch.testing.assert_close(out[i], expected, rtol=0, atol=1e-6)
    # A point exactly on a vertex reads that vertex's row alone.
    vertex = (1001, 1777, 1999)
    on_vertex = fn(torch.tensor([[[c / res for c in vertex]]]), tables, cfg)
    row = (vertex[0] ^ vertex[1] * PRIMES[1] ^ vertex[2] * PRIMES[2]) % t
    assert torch.equal(on_vertex[0, 0], tables[0, 0, row])


# ----------------------------------------------------------------------------- kernel vs reference


@pytest.mark.parametrize(
    "cfg, dtype",
    [(PAPER, torch.float32), (MIXED, torch.float32), (WIDE, torch.float32), (NARROW, torch.float32),
     (MIXED, torch.float64)],
    ids=["paper-hashed-f2", "mixed-dense-hashed-f2", "f4", "f1", "float64"],
)
def test_kernel_matches_reference(cfg, dtype, kernel):
    points = _awkward_points(cfg, batch=2, n=1237, dtype=dtype)
    tables = _random_tables(cfg, 2, dtype=dtype)
    assert uses_kernel(points, cfg)
    upstream = torch.randn(2, 1237, cfg.output_dim, dtype=dtype, generator=torch.Generator().manual_seed(2))
    out_k, gp_k, gt_k = _grads(encode, points, tables, cfg, upstream)
    out_r, gp_r, gt_r = _grads(encode_reference, points, tables, cfg, upstream)
    assert out_k.dtype == dtype and out_k.shape == (2, 1237, cfg.output_dim)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    _close(out_k, out_r, tol)
    _close(gp_k, gp_r, tol)
    _close(gt_k, gt_r, tol)


def test_only_the_requested_gradient(kernel):
    points = _awkward_points(MIXED, 1, 301)
    tables = _random_tables(MIXED, 1)
    upstream = torch.randn(1, 301, MIXED.output_dim)
    (gp,) = torch.autograd.grad(encode(points, tables.detach(), MIXED), points, upstream)
    (gp_r,) = torch.autograd.grad(encode_reference(points, tables.detach(), MIXED), points, upstream)
    _close(gp, gp_r, 1e-5)
    (gt,) = torch.autograd.grad(encode(points.detach(), tables, MIXED), tables, upstream)
    (gt_r,) = torch.autograd.grad(encode_reference(points.detach(), tables, MIXED), tables, upstream)
    _close(gt, gt_r, 1e-5)


def test_boundary_points_are_finite_in_range_and_consistent(kernel):
    """Points at 0, 1, on every level's cell borders and outside the box."""
    cfg = MIXED
    coords = {0.0, 1.0, float(torch.tensor(1.0).nextafter(torch.tensor(0.0)))}
    for res in cfg.resolutions:
        coords |= {k / res for k in range(res + 1)}
    c = torch.tensor(sorted(coords))
    points = torch.stack([c, c.flip(0), c.roll(7)], dim=-1).unsqueeze(0).requires_grad_()
    tables = _random_tables(cfg, 1)
    out_k, gp_k, gt_k = _grads(encode, points, tables, cfg, torch.ones(1, len(c), cfg.output_dim))
    # The reference indexes with index_select, which raises on any out-of-range row.
    out_r, gp_r, gt_r = _grads(encode_reference, points, tables, cfg, torch.ones(1, len(c), cfg.output_dim))
    for t in (out_k, gp_k, gt_k):
        assert torch.isfinite(t).all()
    _close(out_k, out_r, 1e-5)
    _close(gp_k, gp_r, 1e-5)
    _close(gt_k, gt_r, 1e-5)


@pytest.mark.parametrize("impl", ["kernel", "reference"])
def test_outside_points_clamp_and_get_zero_gradient(impl, request):
    fn = _impl(request, impl)
    cfg = MIXED
    tables = _random_tables(cfg, 1).detach()
    outside = torch.tensor([[[-0.5, 0.3, 1.7], [2.0, -1e-3, 0.5], [float("nan"), 0.2, 0.4]]], requires_grad=True)
    clamped = torch.tensor([[[0.0, 0.3, 1.0], [1.0, 0.0, 0.5], [0.0, 0.2, 0.4]]])
    out = fn(outside, tables, cfg)
    torch.testing.assert_close(out, fn(clamped, tables, cfg))
    (grad,) = torch.autograd.grad(out.sum(), outside)
    inside = torch.tensor([[[0, 1, 0], [0, 0, 1], [0, 1, 1]]], dtype=torch.bool)
    assert (grad[~inside] == 0).all() and (grad[inside] != 0).all()


def test_each_object_uses_its_own_tables(kernel):
    cfg = MIXED
    points = _awkward_points(cfg, 3, 200).detach()
    tables = _random_tables(cfg, 3).detach()
    tables[1] = 0
    out = encode(points, tables, cfg)
    assert (out[1] == 0).all() and (out[0] != 0).any()
    for b in range(3):
        torch.testing.assert_close(out[b : b + 1], encode(points[b : b + 1], tables[b : b + 1], cfg))
    tables.requires_grad_()
    upstream = torch.zeros(3, 200, cfg.output_dim)
    upstream[2] = 1
    (grad,) = torch.autograd.grad(encode(points, tables, cfg), tables, upstream)
    assert (grad[:2] == 0).all() and grad[2].abs().sum() > 0


def test_table_gradient_is_deterministic(kernel):
    points = _awkward_points(PAPER, 1, 40000).detach()
    tables = _random_tables(PAPER, 1)
    upstream = torch.randn(1, 40000, PAPER.output_dim)
    first = torch.autograd.grad(encode(points, tables, PAPER), tables, upstream)[0]
    second = torch.autograd.grad(encode(points, tables, PAPER), tables, upstream)[0]
    assert torch.equal(first, second)


def test_gradcheck_kernel_and_reference_float64(kernel):
    cfg = HashGridConfig(levels=3, log2_table_size=6, features=2, base_resolution=2, finest_resolution=12)
    assert cfg.dense[0] and not cfg.dense[-1]
    g = torch.Generator().manual_seed(3)
    # Keep clear of cell borders, where the point derivative jumps and finite differences straddle it.
    points = (torch.rand(2, 9, 3, generator=g, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    for res in cfg.resolutions:
        frac = (points.detach() * res) % 1
        assert ((frac > 1e-4) & (frac < 1 - 1e-4)).all()
    tables = torch.randn(2, *cfg.table_shape, generator=g, dtype=torch.float64, requires_grad=True)
    for fn in (encode, encode_reference):
        assert torch.autograd.gradcheck(lambda p, t: fn(p, t, cfg), (points, tables), eps=1e-6, atol=1e-6)


def test_half_precision_inputs_under_autocast(kernel):
    cfg = MIXED
    points = _awkward_points(cfg, 1, 500).detach().bfloat16().requires_grad_()
    tables = _random_tables(cfg, 1).detach().bfloat16().requires_grad_()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = encode(points, tables, cfg)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()
    torch.testing.assert_close(out, encode_reference(points.float(), tables.float(), cfg), rtol=1e-5, atol=1e-5)
    grad_points, grad_tables = torch.autograd.grad(out.sum(), (points, tables))
    assert grad_points.dtype == torch.bfloat16 and grad_tables.dtype == torch.bfloat16
    assert torch.isfinite(grad_points.float()).all() and torch.isfinite(grad_tables.float()).all()
    half = encode(points.detach().half(), tables.detach().half(), cfg)
    assert half.dtype == torch.float32 and torch.isfinite(half).all()


def test_pure_torch_switch(monkeypatch, kernel):
    points = torch.rand(1, 10, 3)
    assert uses_kernel(points, PAPER)
    monkeypatch.setenv("HYPNERF_PURE_TORCH", "1")
    assert not uses_kernel(points, PAPER)
    tables = _random_tables(PAPER, 1).detach()
    torch.testing.assert_close(encode(points, tables, PAPER), encode_reference(points, tables, PAPER))


def test_shape_errors():
    with pytest.raises(ValueError):
        encode(torch.rand(10, 3), init_tables(PAPER, 1), PAPER)
    with pytest.raises(ValueError):
        encode(torch.rand(2, 10, 3), init_tables(PAPER, 1), PAPER)
    with pytest.raises(ValueError):
        encode(torch.rand(1, 10, 3), init_tables(MIXED, 1), PAPER)


# ----------------------------------------------------------------------------- build cache


def test_stale_builds_are_pruned_and_recent_ones_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("HYPNERF_CACHE", str(tmp_path))
    old_time = time.time() - 40 * 86400
    folders = {}
    for name in ("hashgrid_current", "hashgrid_recent", "hashgrid_stale", "hashgrid_died", "other_stale"):
        folder = tmp_path / name
        folder.mkdir()
        if name != "hashgrid_died":
            (folder / f"{name}.so").write_bytes(b"")
        folders[name] = folder
    for name in ("hashgrid_current", "hashgrid_stale", "other_stale"):
        os.utime(folders[name] / f"{name}.so", (old_time, old_time))
    os.utime(folders["hashgrid_died"], (old_time, old_time))
    removed = kernels.prune_stale_builds("hashgrid", keep=folders["hashgrid_current"])
    assert sorted(p.name for p in removed) == ["hashgrid_died", "hashgrid_stale"]
    # the build in use survives however old, other extensions and recently used builds too
    assert all(folders[n].exists() for n in ("hashgrid_current", "hashgrid_recent", "other_stale"))
    assert not folders["hashgrid_stale"].exists() and not folders["hashgrid_died"].exists()


def test_build_key_tracks_sources_and_cache_env(tmp_path, monkeypatch):
    monkeypatch.setenv("HYPNERF_CACHE", str(tmp_path / "cache"))
    assert kernels.cache_root() == tmp_path / "cache"
    assert kernels.library_path("hashgrid").parent.parent == tmp_path / "cache"
    csrc = tmp_path / "csrc"
    shutil.copytree(kernels.CSRC, csrc)
    monkeypatch.setattr(kernels, "CSRC", csrc)
    before = kernels.build_key()
    (csrc / "hashgrid_common.h").write_text((csrc / "hashgrid_common.h").read_text() + "\n// edited\n")
    assert kernels.build_key() != before
