"""Functional, batched multi-resolution hash encoding (InstantNGP / torch-ngp semantics).

The tables are an argument, ``[B, L, T, F]``, because the hypernetwork emits them: object ``b``'s
points ``[B, N, 3]`` are looked up in its own tables only. ``encode`` returns ``[B, N, L*F]``
with features ordered level-major (level ``l`` occupies ``l*F:(l+1)*F``).

Precise semantics (shared by both implementations below):

- Level ``l`` has ``res_l = floor(N_min * b**l)`` cells per axis (``res_l + 1`` vertices), with
  ``b = exp((ln N_max - ln N_min) / (L - 1))``; the floor tolerates 1e-9 of rounding so the
  finest level is exactly ``N_max``.
- A level is stored densely while ``(res + 1)**3 <= T``, at row ``x + y (res+1) + z (res+1)**2``;
  otherwise at row ``(x * 1 ^ y * 2654435761 ^ z * 805459861) mod T``, formed in int64.
- Coordinates are clamped into ``[0, 1]`` first (NaN is treated as 0). A point's cell is
  ``min(floor(x * res), res - 1)``, so ``x = 1`` lies in the last cell with fraction 1 and every
  corner stays inside the grid; on an inner cell border the point belongs to the upper cell.
- Trilinear interpolation of the 8 corners. The gradient with respect to the points is the
  derivative of the trilinear weights (one-sided on a cell border, as just defined) times
  ``res``; it is zero for coordinates outside ``[0, 1]`` or NaN and passes at exactly 0 and 1.
- dtype: float16/bfloat16 inputs (e.g. under autocast) are upcast and the work is done in
  float32, returning float32; float64 inputs are computed and returned in float64 (used by
  gradcheck). Gradients reach the inputs in their own dtype.

Two implementations: the fused C++/OpenMP CPU kernel (``model/csrc/hashgrid.cpp``, built by
``model.nerf.encodings.kernels``), used for CPU tensors; and a pure-PyTorch reference, used on CUDA and other
devices, when the kernel cannot be built, when ``HYPNERF_PURE_TORCH=1``, and as the golden
reference in the tests. The kernel path supports first-order gradients only (pose refinement and
training need no more); the reference path is differentiable to any order.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from dataclasses import dataclass

import torch

from model.nerf.encodings import kernels

log = logging.getLogger(__name__)

PRIMES = (1, 2654435761, 805459861)
# Largest table the kernel indexes with 32-bit row numbers (the uint32 hash is exact up to 2^32).
MAX_LOG2_TABLE_SIZE = 24
# Finest resolution accepted: float32 positions still resolve fractions of a cell well below it.
MAX_RESOLUTION = 2**20 - 1
KERNEL_FEATURES = (1, 2, 4, 8)


@dataclass(frozen=True)
class HashGridConfig:
    """Shape of a multi-resolution hash grid: L levels of T = 2**log2_table_size rows of F features."""

    levels: int = 16
    log2_table_size: int = 11
    features: int = 2
    base_resolution: int = 16
    finest_resolution: int = 2048

    def __post_init__(self) -> None:
        if self.levels < 1 or self.features < 1:
            raise ValueError("levels and features must be positive")
        if not 1 <= self.log2_table_size <= MAX_LOG2_TABLE_SIZE:
            raise ValueError(f"log2_table_size must lie in [1, {MAX_LOG2_TABLE_SIZE}]")
        if not 1 <= self.base_resolution <= self.finest_resolution <= MAX_RESOLUTION:
            raise ValueError(f"need 1 <= base_resolution <= finest_resolution <= {MAX_RESOLUTION}")
        if self.levels == 1 and self.finest_resolution != self.base_resolution:
            raise ValueError("a single level needs finest_resolution == base_resolution")

    @property
    def table_size(self) -> int:
        return 1 << self.log2_table_size

    @property
    def output_dim(self) -> int:
        return self.levels * self.features

    @property
    def table_shape(self) -> tuple[int, int, int]:
        """Per-object table shape ``(L, T, F)``; a batch is ``(B, *table_shape)``."""
        return (self.levels, self.table_size, self.features)

    @property
    def per_level_scale(self) -> float:
        if self.levels == 1:
            return 1.0
        return math.exp((math.log(self.finest_resolution) - math.log(self.base_resolution)) / (self.levels - 1))

    @functools.cached_property
    def resolutions(self) -> tuple[int, ...]:
        """Cells per axis of each level."""
        log_b = math.log(self.per_level_scale)
        return tuple(
            math.floor(math.exp(math.log(self.base_resolution) + level * log_b) + 1e-9) for level in range(self.levels)
        )

    @functools.cached_property
    def dense(self) -> tuple[bool, ...]:
        """Whether each level is stored densely (its (res+1)^3 vertices fit the table)."""
        return tuple((r + 1) ** 3 <= self.table_size for r in self.resolutions)


def init_tables(
    cfg: HashGridConfig, batch: int, generator: torch.Generator | None = None, device: torch.device | str | None = None
) -> torch.Tensor:
    """Float32 tables ``[batch, L, T, F]`` drawn from U(-1e-4, 1e-4), as torch-ngp initialises them."""
    tables = torch.empty((batch, *cfg.table_shape), dtype=torch.float32, device=device)
    return tables.uniform_(-1e-4, 1e-4, generator=generator)


def _compute_dtype(*tensors: torch.Tensor) -> torch.dtype:
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


def encode_reference(points: torch.Tensor, tables: torch.Tensor, cfg: HashGridConfig) -> torch.Tensor:
    """Pure-PyTorch encoding with the module's semantics; differentiable to any order by autograd."""
    _check(points, tables, cfg)
    dtype = _compute_dtype(points, tables)
    # nan_to_num then clamp: NaN -> 0, and the gradient passes only for coordinates in [0, 1].
    x = torch.nan_to_num(points.to(dtype), nan=0.0).clamp(0.0, 1.0)
    tables = tables.to(dtype)
    batch, n = x.shape[:2]
    t = cfg.table_size
    # Corner offsets in the kernel's order: bit 0 is +x, bit 1 +y, bit 2 +z.
    offsets = torch.tensor([[(c >> d) & 1 for d in range(3)] for c in range(8)], device=x.device)
    row_base = (torch.arange(batch, device=x.device) * t).view(batch, 1, 1)
    out = []
    for level, (res, dense) in enumerate(zip(cfg.resolutions, cfg.dense)):
        pos = x * res
        cell = pos.detach().floor().clamp(max=res - 1)
        frac = pos - cell
        vertex = cell.long().unsqueeze(2) + offsets  # [B, N, 8, 3], int64
        if dense:
            rows = vertex[..., 0] + vertex[..., 1] * (res + 1) + vertex[..., 2] * (res + 1) ** 2
        else:
            rows = (vertex[..., 0] * PRIMES[0]) ^ (vertex[..., 1] * PRIMES[1]) ^ (vertex[..., 2] * PRIMES[2])
            rows = rows & (t - 1)
        corners = tables[:, level].reshape(batch * t, cfg.features).index_select(0, (rows + row_base).view(-1))
        corners = corners.view(batch, n, 8, cfg.features)
        axis_w = torch.where(offsets.bool(), frac.unsqueeze(2), 1.0 - frac.unsqueeze(2))  # [B, N, 8, 3]
        weights = axis_w.prod(dim=-1, keepdim=True)
        out.append((weights * corners).sum(dim=2))
    return torch.cat(out, dim=-1)


class _HashGridFunction(torch.autograd.Function):
    """Autograd wrapper around the fused CPU kernel (first-order gradients for tables and points)."""

    @staticmethod
    def forward(ctx, points, tables, resolutions, dense):
        ctx.save_for_backward(points, tables)
        ctx.levels = (resolutions, dense)
        return _kernel_ops().forward(points, tables, resolutions, dense)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        points, tables = ctx.saved_tensors
        need_points, need_tables = ctx.needs_input_grad[:2]
        grad_tables, grad_points = _kernel_ops().backward(
            grad.contiguous(), points, tables, *ctx.levels, need_tables, need_points
        )
        return (grad_points if need_points else None), (grad_tables if need_tables else None), None, None


# Why the kernel is unavailable in this process, once a build or load has failed.
_KERNEL_FAILURE: list[str] = []


def _kernel_ops():
    return kernels.hashgrid_ops()


def _kernel_available() -> bool:
    """Whether the fused kernel can be used, building it on first call; warns once if not."""
    if _KERNEL_FAILURE:
        return False
    try:
        _kernel_ops()
    except Exception as exc:  # any build or load failure means the slow path, not a crash
        _KERNEL_FAILURE.append(f"{type(exc).__name__}: {exc}")
        log.warning(
            "hash encoding: the C++ kernel could not be built or loaded (%s); falling back to the "
            "pure-PyTorch reference, which is about 50x slower on CPU",
            _KERNEL_FAILURE[0].splitlines()[0],
        )
        return False
    return True


def uses_kernel(points: torch.Tensor, cfg: HashGridConfig) -> bool:
    """Whether ``encode`` will run the fused kernel for these inputs."""
    return (
        points.device.type == "cpu"
        and cfg.features in KERNEL_FEATURES
        and os.environ.get("HYPNERF_PURE_TORCH", "0") != "1"
        and _kernel_available()
    )


def encode(points: torch.Tensor, tables: torch.Tensor, cfg: HashGridConfig) -> torch.Tensor:
    """Encode points ``[B, N, 3]`` in ``[0, 1]^3`` with tables ``[B, L, T, F]`` into ``[B, N, L*F]``."""
    if not uses_kernel(points, cfg):
        return encode_reference(points, tables, cfg)
    _check(points, tables, cfg)
    dtype = _compute_dtype(points, tables)
    return _HashGridFunction.apply(
        points.to(dtype).contiguous(),
        tables.to(dtype).contiguous(),
        list(cfg.resolutions),
        [int(d) for d in cfg.dense],
    )


def _check(points: torch.Tensor, tables: torch.Tensor, cfg: HashGridConfig) -> None:
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must be [B, N, 3], got {tuple(points.shape)}")
    if tables.dim() != 4 or tuple(tables.shape[1:]) != cfg.table_shape or tables.shape[0] != points.shape[0]:
        expected = (points.shape[0], *cfg.table_shape)
        raise ValueError(f"tables must be {list(expected)}, got {list(tables.shape)}")
    if points.device != tables.device:
        raise ValueError("points and tables must be on the same device")
