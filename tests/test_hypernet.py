"""The hypernetwork: emitted shapes, routing of shape and colour codes, presets, gradients."""

from __future__ import annotations

import math

import json

import pytest
import torch

from model.nerf import config
from model.nerf.fields.hashgrid import FieldConfig, validate_params
from model.prior.hypernet import HyperNetConfig, HyperNetwork, code_penalty, preset, spread_noise
from model.nerf.fields.positional import PEFieldConfig


@pytest.fixture
def tiny() -> HyperNetConfig:
    return preset("tiny")


def test_emitted_parameters_match_the_field(tiny):
    net = HyperNetwork(tiny, instances=5)
    params = net(torch.tensor([0, 3, 4]))
    assert validate_params(tiny.field, params) == 3
    assert all(torch.isfinite(v).all() for v in params.values())


def test_a_fresh_prior_emits_a_template_nerf_plus_small_perturbations(tiny):
    net = HyperNetwork(tiny, instances=4, seed=1)
    params = net(torch.arange(4))
    for name, value in params.items():
        template = net.heads[name].out.bias.reshape(value.shape[1:])
        # the template is a freshly initialised NeRF: the field's own init bounds
        assert 0 < template.abs().max() <= (1e-4 if name == "tables" else 1.0) * 1.0001, name
        spread = (value - template).abs().max()
        assert 0 < spread < 0.5 * template.abs().max(), name


def test_shape_code_drives_geometry_and_colour_code_drives_colour(tiny):
    net = HyperNetwork(tiny, instances=3)
    shape0, colour0 = net.codes(torch.tensor([0]))
    shape1, colour1 = net.codes(torch.tensor([1]))
    base = net.params_from_codes(shape0, colour0)
    new_colour = net.params_from_codes(shape0, colour1)
    new_shape = net.params_from_codes(shape1, colour0)
    for name in tiny.field.shape_param_names():
        assert torch.equal(base[name], new_colour[name])
        assert not torch.equal(base[name], new_shape[name])
    for name in tiny.field.color_param_names():
        assert torch.equal(base[name], new_shape[name])
        assert not torch.equal(base[name], new_colour[name])


def test_colour_variants_share_a_shape_code(tiny):
    net = HyperNetwork(tiny, instances=4, shape_index=[0, 0, 1, 1])
    assert net.shape_codes.num_embeddings == 2
    params = net(torch.tensor([0, 1, 2]))
    assert torch.equal(params["tables"][0], params["tables"][1])
    assert not torch.equal(params["tables"][0], params["tables"][2])
    assert not torch.equal(params["color2"][0], params["color2"][1])


def test_bad_shape_index_is_rejected(tiny):
    with pytest.raises(ValueError, match="shape_index"):
        HyperNetwork(tiny, instances=3, shape_index=[0, 1])
    with pytest.raises(ValueError, match="at least one instance"):
        HyperNetwork(tiny, instances=0)


def test_gradients_reach_codes_and_every_head(tiny):
    net = HyperNetwork(tiny, instances=3)
    index = torch.tensor([1, 2])
    params = net(index)
    loss = sum(v.square().mean() for v in params.values()) + code_penalty(*net.codes(index))
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert net.color_codes.weight.grad[1:].abs().sum() > 0 and net.color_codes.weight.grad[0].abs().sum() == 0


def test_table_rank_bounds_the_table_head():
    cfg = HyperNetConfig(field=preset("tiny").field, shape_code_dim=8, color_code_dim=8, head_hidden=64, head_layers=1, table_rank=4)
    net = HyperNetwork(cfg, instances=2)
    table_outputs = math.prod(cfg.field.param_shapes()["tables"])
    expected = (8 * 64 + 64) + 64 * 4 + (4 * table_outputs + table_outputs)
    assert net.head_parameter_counts()["tables"] == expected


def test_presets_serialise_and_emit_their_fields():
    for name in ("paper", "cpu", "cpu-no-mrhe", "tiny"):
        cfg = preset(name)
        assert config.from_dict(HyperNetConfig, json.loads(json.dumps(config.to_dict(cfg)))) == cfg
    assert isinstance(preset("cpu-no-mrhe").field, PEFieldConfig)
    paper = preset("paper")
    assert (paper.shape_code_dim, paper.color_code_dim, paper.head_hidden, paper.head_layers) == (512, 512, 512, 3)
    assert paper.field == FieldConfig()  # L=16, T=2^11, F=2
    with pytest.raises(ValueError, match="unknown preset"):
        preset("huge")


def test_paper_table_head_is_the_large_one():
    net = HyperNetwork(preset("paper"), instances=2)
    counts = net.head_parameter_counts()
    assert counts["tables"] == 3 * (512 * 512 + 512) + 512 * 65536 + 65536  # 3 hidden layers of 512, then L*T*F outputs
    assert counts["tables"] > 3 * sum(v for k, v in counts.items() if k != "tables")


def test_no_mrhe_prior_emits_the_positional_field():
    cfg = preset("cpu-no-mrhe")
    net = HyperNetwork(HyperNetConfig(field=cfg.field, shape_code_dim=8, color_code_dim=8, head_hidden=16, head_layers=1, table_rank=None), instances=2)
    params = net(torch.tensor([0, 1]))
    assert set(params) == set(cfg.field.param_shapes())


def test_code_noise_follows_the_codebook_spread_and_is_seeded(tiny):
    net = HyperNetwork(tiny, instances=6, seed=2)
    with torch.no_grad():
        net.shape_codes.weight.mul_(torch.linspace(0.1, 3.0, tiny.shape_code_dim))  # a spread per dimension
    index = torch.arange(6)
    plain = net(index)
    assert all(torch.equal(plain[k], v) for k, v in net(index, 0.0).items())  # no noise: the codebook's own NeRFs
    a = net(index, 0.5, torch.Generator().manual_seed(3))
    b = net(index, 0.5, torch.Generator().manual_seed(3))
    assert all(torch.equal(a[k], b[k]) for k in a) and any(not torch.allclose(a[k], plain[k]) for k in a)
    book = net.shape_codes.weight
    noise = spread_noise(torch.zeros(20000, book.shape[1]), book, torch.Generator().manual_seed(0))
    ratio = noise.std(dim=0) / book.detach().std(dim=0)
    assert torch.allclose(ratio, torch.ones_like(ratio), atol=0.05)  # per dimension, the codebook's spread
    assert noise.requires_grad is False


def test_code_noise_keeps_gradients_on_the_codes(tiny):
    net = HyperNetwork(tiny, instances=3)
    params = net(torch.tensor([0, 2]), 0.5, torch.Generator().manual_seed(0))
    sum(v.float().sum() for v in params.values()).backward()
    assert net.shape_codes.weight.grad is not None and net.shape_codes.weight.grad.abs().sum() > 0
    assert net.color_codes.weight.grad[[0, 2]].abs().sum() > 0 and net.color_codes.weight.grad[1].abs().sum() == 0
