"""Storage of a category: the prior against per-object fits, at equal precision and equal sharing.

The prior is a fixed set of heads plus one shape code per mesh and one colour code per instance;
per-object fits given the same sharing store one set of geometry tensors (hash tables and density
net) per mesh and one colour net per instance. Both are counted in parameters times the bytes of
one value at a stated precision, so the figures are exact consequences of the architectures (a
design fact, not a measurement): the prior's curve has a large intercept and a small slope, the
fits' a zero intercept and a large slope, and the crossover says how many instances the prior
needs before it is the smaller of the two.
"""

from __future__ import annotations

import math

from model.nerf.fields import Field
from model.prior.hypernet import HyperNetConfig


def _count(field_cfg: Field, names: list[str]) -> int:
    shapes = field_cfg.param_shapes()
    return sum(math.prod(shapes[name]) for name in names)


def storage_model(hypernet_cfg: HyperNetConfig, head_parameters: int, fit_field: Field, bytes_per_value: int = 2) -> dict:
    """Per-item costs in bytes: the prior's fixed heads and per-shape / per-instance codes, and a
    fit's per-shape geometry and per-instance colour tensors (or its whole field, unshared)."""
    geometry = _count(fit_field, fit_field.shape_param_names())
    colour = _count(fit_field, fit_field.color_param_names())
    return {
        "bytes_per_value": bytes_per_value,
        "prior_fixed": head_parameters * bytes_per_value,
        "prior_per_shape": hypernet_cfg.shape_code_dim * bytes_per_value,
        "prior_per_instance": hypernet_cfg.color_code_dim * bytes_per_value,
        "fit_per_shape": geometry * bytes_per_value,
        "fit_per_instance": colour * bytes_per_value,
        "fit_unshared_per_instance": (geometry + colour) * bytes_per_value,
    }


def storage_curve(model: dict, instances: list[int], variants_per_shape: float) -> list[dict]:
    """Bytes of the prior, of shared fits and of unshared fits for each number of instances."""
    rows = []
    for n in instances:
        shapes = n / variants_per_shape
        rows.append(
            {
                "instances": n,
                "prior_bytes": model["prior_fixed"] + shapes * model["prior_per_shape"] + n * model["prior_per_instance"],
                "fits_shared_bytes": shapes * model["fit_per_shape"] + n * model["fit_per_instance"],
                "fits_unshared_bytes": n * model["fit_unshared_per_instance"],
            }
        )
    return rows


def crossover_instances(model: dict, variants_per_shape: float) -> float:
    """Instances from which the prior is smaller than shared fits (``inf`` if never)."""
    prior_slope = model["prior_per_shape"] / variants_per_shape + model["prior_per_instance"]
    fit_slope = model["fit_per_shape"] / variants_per_shape + model["fit_per_instance"]
    return model["prior_fixed"] / (fit_slope - prior_slope) if fit_slope > prior_slope else math.inf
