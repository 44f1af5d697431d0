"""Sample positions along rays: stratified distances between each ray's entry and exit."""

from __future__ import annotations

import torch


def stratified_distances(
    near: torch.Tensor,
    far: torch.Tensor,
    count: int,
    *,
    start: int = 0,
    stop: int | None = None,
    jitter: bool = False,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples ``start..stop`` of ``count`` stratified distances per ray in ``[near, far]``, and the
    interval length each sample stands for.

    Without jitter the samples sit at interval midpoints (deterministic renders); with jitter each
    is uniform inside its interval (training). Returns ``t [R, stop - start]`` and ``delta [R]``;
    rays with ``far <= near`` get ``delta = 0`` so they contribute nothing. Asking for a slice lets
    a renderer march in segments without materialising every sample of every ray.
    """
    stop = count if stop is None else stop
    span = (far - near).clamp_min(0.0)
    delta = span / count
    offsets = torch.arange(start, stop, device=near.device, dtype=near.dtype)
    if jitter:
        offsets = offsets + torch.rand(near.shape[0], stop - start, device=near.device, dtype=near.dtype, generator=generator)
    else:
        offsets = offsets + 0.5
    return near[:, None] + offsets * delta[:, None], delta
