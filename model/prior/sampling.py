"""Moving through a prior's code space: interpolation between codes, and unconditional samples
from a density fitted on the codebook (the paper's second limitation, section 5).

The density is a **scikit-learn** ``GaussianMixture`` per codebook (shape codes, colour codes),
with diagonal covariances: the codebooks hold tens to hundreds of 128-d codes, far too few for
full covariances. The number of components is chosen by BIC among :data:`COMPONENT_CHOICES`.
Samples are drawn with a ``temperature`` that scales each component's spread (1 is the fitted
density; smaller stays nearer the component means). Shape and colour are drawn independently,
as the prior's routing keeps them apart.

A fitted density is plain JSON (weights, means, variances), so a sample is reproducible from the
file and its seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

COMPONENT_CHOICES = (1, 2, 4, 8)


def interpolate(a: torch.Tensor, b: torch.Tensor, steps: int) -> torch.Tensor:
    """``steps`` codes on the straight line from ``a [D]`` to ``b [D]``, ends included: ``[steps, D]``."""
    if steps < 2:
        raise ValueError(f"an interpolation needs at least 2 steps (the two ends), got {steps}")
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"interpolate two codes of one shape [D], got {tuple(a.shape)} and {tuple(b.shape)}")
    t = torch.linspace(0.0, 1.0, steps, dtype=a.dtype, device=a.device)[:, None]
    return (1.0 - t) * a[None] + t * b[None]


@dataclass
class DensityConfig:
    """Fitting: ``components`` (None: chosen by BIC), variance floor ``reg``, seed."""

    components: int | None = None
    reg: float = 1e-4
    seed: int = 0


@dataclass
class GaussianMixtureDensity:
    """A diagonal Gaussian mixture: ``weights [K]``, ``means [K, D]``, ``variances [K, D]``."""

    weights: np.ndarray
    means: np.ndarray
    variances: np.ndarray

    def sample(self, count: int, rng: np.random.Generator, temperature: float = 1.0) -> np.ndarray:
        """``count`` samples ``[count, D]``; each component's spread scaled by ``temperature``."""
        if count < 1:
            raise ValueError(f"draw at least one sample, got {count}")
        if not temperature > 0:
            raise ValueError(f"temperature must be positive, got {temperature}")
        component = rng.choice(len(self.weights), size=count, p=self.weights / self.weights.sum())
        noise = rng.standard_normal((count, self.means.shape[1]))
        return self.means[component] + noise * np.sqrt(self.variances[component]) * temperature

    def to_json(self) -> dict:
        return {"weights": self.weights.tolist(), "means": self.means.tolist(), "variances": self.variances.tolist()}

    @classmethod
    def from_json(cls, data: dict) -> GaussianMixtureDensity:
        return cls(np.asarray(data["weights"], float), np.asarray(data["means"], float), np.asarray(data["variances"], float))


def fit_density(codes: np.ndarray, cfg: DensityConfig) -> GaussianMixtureDensity:
    """A diagonal Gaussian mixture fitted to ``codes [N, D]`` (components by BIC unless given)."""
    from sklearn.mixture import GaussianMixture

    codes = np.asarray(codes, dtype=np.float64)
    if codes.ndim != 2 or len(codes) < 2:
        raise ValueError(f"fitting a density needs at least 2 codes [N, D], got shape {codes.shape}")
    if not np.isfinite(codes).all():
        raise ValueError("the codebook holds NaN or Inf values; the prior is broken")
    choices = [cfg.components] if cfg.components else [k for k in COMPONENT_CHOICES if k <= len(codes) // 2] or [1]
    best, best_bic = None, np.inf
    for k in choices:
        model = GaussianMixture(k, covariance_type="diag", reg_covar=cfg.reg, random_state=cfg.seed, n_init=2).fit(codes)
        bic = model.bic(codes)
        if bic < best_bic:
            best, best_bic = model, bic
    return GaussianMixtureDensity(best.weights_.copy(), best.means_.copy(), best.covariances_.copy())


@dataclass
class CodeDensity:
    """Independent densities of shape codes and colour codes."""

    shape: GaussianMixtureDensity
    color: GaussianMixtureDensity

    @classmethod
    def fit(cls, shape_codes: torch.Tensor, color_codes: torch.Tensor, cfg: DensityConfig | None = None) -> CodeDensity:
        cfg = cfg or DensityConfig()
        return cls(fit_density(shape_codes.detach().cpu().numpy(), cfg), fit_density(color_codes.detach().cpu().numpy(), cfg))

    def sample(self, count: int, seed: int = 0, temperature: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` (shape ``[count, S]``, colour ``[count, C]``) float32 codes."""
        rng = np.random.default_rng(seed)
        shape = self.shape.sample(count, rng, temperature)
        color = self.color.sample(count, rng, temperature)
        return torch.from_numpy(shape).float(), torch.from_numpy(color).float()

    def to_json(self) -> dict:
        return {"shape": self.shape.to_json(), "color": self.color.to_json()}

    @classmethod
    def from_json(cls, data: dict) -> CodeDensity:
        return cls(GaussianMixtureDensity.from_json(data["shape"]), GaussianMixtureDensity.from_json(data["color"]))


def nearest_code_distance(samples: torch.Tensor, codebook: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance of each sample ``[N, D]`` to its nearest codebook entry ``[M, D]``, divided by the
    codebook's median nearest-neighbour spacing (1 = as far as training codes are from each other):
    ``(relative distance [N], nearest index [N])``."""
    distances = torch.cdist(samples.float(), codebook.float())
    nearest, index = distances.min(dim=1)
    return nearest / codebook_spacing(codebook), index


def codebook_spacing(codebook: torch.Tensor) -> float:
    """Median distance from each codebook entry to its nearest other entry."""
    if len(codebook) < 2:
        raise ValueError("a codebook spacing needs at least two codes")
    own = torch.cdist(codebook.float(), codebook.float())
    own.fill_diagonal_(float("inf"))
    return float(own.min(dim=1).values.median().clamp_min(1e-12))
