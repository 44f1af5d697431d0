"""The hypernetwork M: per-object shape and colour codes -> every parameter of a NeRF.

Paper section 3.1, step 1. Two auto-decoded codebooks (``nn.Embedding``) hold a shape code S_n
and a colour code C_n per training instance; one head per emitted tensor (an MLP) maps a code to
that tensor. Routing follows the field's own split: the shape code drives the geometry tensors
(hash tables and density net of the hash-grid field), the colour code drives the colour net, so
swapping codes between instances swaps shape and colour independently.

Heads start as "template + small perturbation": the final layer's bias is a freshly initialised
NeRF (what a per-object fit would start from) and its weight is scaled down, so every instance
begins as a valid NeRF and the codes move it from there (the hyper-weight init of SIREN-style
hypernetworks). The table head is by far the largest (``hidden x L*T*F``); ``table_rank`` puts a
narrow linear bottleneck in front of its output, which keeps the exported prior small enough to
ship while still giving each of the category's shapes its own tables.

Instances of one mesh that differ only in colour (dataset variants) may share one shape code
(``shape_index`` maps instances to shape codes); the colour code stays per instance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import nn

from model.nerf import config
from model.nerf.fields import Field, FieldConfig, FieldParams, PEFieldConfig


@dataclass
class HyperNetConfig:
    """Sizes of the codes and heads, and the field the heads emit."""

    field: Field = field(default_factory=FieldConfig)
    shape_code_dim: int = 128
    color_code_dim: int = 128
    head_hidden: int = 256
    head_layers: int = 2
    table_rank: int | None = 128
    final_init_scale: float = 0.1
    code_init_std: float = 0.1


def _presets() -> dict[str, HyperNetConfig]:
    return {
        # the official code's sizes: codes 512 + 512, every head 3 hidden layers of 512
        "paper": HyperNetConfig(shape_code_dim=512, color_code_dim=512, head_hidden=512, head_layers=3, table_rank=None),
        # sized for 2 CPU cores and a prior that ships in a small bundle (see BENCHMARKS.md)
        "cpu": HyperNetConfig(),
        # the ablation without MRHE: same hypernetwork, positional-encoding NeRF with as many emitted parameters
        "cpu-no-mrhe": HyperNetConfig(field=PEFieldConfig(), table_rank=None),
        # for tests: a tiny field and tiny heads
        "tiny": HyperNetConfig(
            field=config.from_dict(
                FieldConfig,
                {"encoding": {"levels": 4, "log2_table_size": 8, "features": 2, "base_resolution": 4, "finest_resolution": 32}, "hidden": 16, "color_hidden": 16}
            ),
            shape_code_dim=16,
            color_code_dim=16,
            head_hidden=32,
            head_layers=1,
            table_rank=16,
        ),
    }


def preset(name: str) -> HyperNetConfig:
    presets = _presets()
    if name not in presets:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(presets)}")
    return presets[name]


PRESET_NAMES = ("paper", "cpu", "cpu-no-mrhe", "tiny")


class Head(nn.Module):
    """An MLP from a code to one emitted tensor: ``[B, code] -> [B, *shape]``."""

    def __init__(self, code_dim: int, shape: tuple[int, ...], hidden: int, layers: int, rank: int | None, template: torch.Tensor, final_scale: float):
        super().__init__()
        self.shape = tuple(shape)
        blocks: list[nn.Module] = []
        width = code_dim
        for _ in range(layers):
            blocks += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        if rank is not None and rank < width:
            blocks.append(nn.Linear(width, rank, bias=False))
            width = rank
        self.body = nn.Sequential(*blocks)
        self.out = nn.Linear(width, math.prod(self.shape))
        with torch.no_grad():
            self.out.weight.mul_(final_scale * template.std().clamp_min(1e-4) * math.sqrt(width))
            self.out.bias.copy_(template.reshape(-1))

    def forward(self, code: torch.Tensor) -> torch.Tensor:
        return self.out(self.body(code)).reshape(code.shape[0], *self.shape)


class HyperNetwork(nn.Module):
    """Codebooks plus heads. ``forward(instances)`` returns batched field parameters ``[B, ...]``."""

    def __init__(self, cfg: HyperNetConfig, instances: int, shape_index: list[int] | None = None, *, seed: int = 0):
        super().__init__()
        if instances < 1:
            raise ValueError("a hypernetwork needs at least one instance")
        self.cfg = cfg
        shape_index = list(range(instances)) if shape_index is None else list(shape_index)
        if len(shape_index) != instances or min(shape_index) < 0:
            raise ValueError("shape_index must give one non-negative shape code per instance")
        self.register_buffer("shape_index", torch.tensor(shape_index, dtype=torch.long))
        generator = torch.Generator().manual_seed(seed)
        shapes = max(shape_index) + 1
        self.shape_codes = nn.Embedding(shapes, cfg.shape_code_dim)
        self.color_codes = nn.Embedding(instances, cfg.color_code_dim)
        with torch.no_grad():
            self.shape_codes.weight.copy_(torch.randn(shapes, cfg.shape_code_dim, generator=generator) * cfg.code_init_std)
            self.color_codes.weight.copy_(torch.randn(instances, cfg.color_code_dim, generator=generator) * cfg.code_init_std)
        template = cfg.field.init_params(1, generator=generator)
        self.shape_names = cfg.field.shape_param_names()
        self.color_names = cfg.field.color_param_names()
        heads = {}
        for name, shape in cfg.field.param_shapes().items():
            code_dim = cfg.shape_code_dim if name in self.shape_names else cfg.color_code_dim
            rank = cfg.table_rank if name == "tables" else None
            heads[name] = Head(code_dim, shape, cfg.head_hidden, cfg.head_layers, rank, template[name][0], cfg.final_init_scale)
        self.heads = nn.ModuleDict(heads)

    @property
    def instances(self) -> int:
        return self.color_codes.num_embeddings

    def codes(self, instances: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Shape and colour codes ``([B, S], [B, C])`` of instance indices ``[B]``."""
        return self.shape_codes(self.shape_index[instances]), self.color_codes(instances)

    def params_from_codes(self, shape_code: torch.Tensor, color_code: torch.Tensor) -> FieldParams:
        """Field parameters of arbitrary codes (mixes, interpolations, optimised codes)."""
        out = {}
        for name, head in self.heads.items():
            out[name] = head(shape_code if name in self.shape_names else color_code)
        return out

    def forward(self, instances: torch.Tensor, code_noise: float = 0.0, generator: torch.Generator | None = None) -> FieldParams:
        """Field parameters of instances ``[B]``; with ``code_noise`` their codes are perturbed by
        Gaussian noise of that many times each codebook's per-dimension spread (training only)."""
        shape_code, color_code = self.codes(instances)
        if code_noise > 0:
            shape_code = shape_code + code_noise * spread_noise(shape_code, self.shape_codes.weight, generator)
            color_code = color_code + code_noise * spread_noise(color_code, self.color_codes.weight, generator)
        return self.params_from_codes(shape_code, color_code)

    def head_parameter_counts(self) -> dict[str, int]:
        counts = {name: sum(p.numel() for p in head.parameters()) for name, head in self.heads.items()}
        counts["shape_codebook"] = self.shape_codes.weight.numel()
        counts["color_codebook"] = self.color_codes.weight.numel()
        return counts


def spread_noise(code: torch.Tensor, book: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """Gaussian noise shaped like ``code [B, D]`` with the per-dimension std of ``book [N, D]``
    (detached: the noise follows the codebook's scale, so codes cannot outgrow it)."""
    spread = book.detach().std(dim=0) if book.shape[0] > 1 else book.detach().abs().mean().expand(book.shape[1])
    return torch.randn(code.shape, generator=generator, device=code.device, dtype=code.dtype) * spread


def code_penalty(shape_code: torch.Tensor, color_code: torch.Tensor) -> torch.Tensor:
    """Mean squared norm of the codes: keeps the auto-decoded codebooks near a compact prior."""
    return shape_code.pow(2).sum(-1).mean() + color_code.pow(2).sum(-1).mean()
