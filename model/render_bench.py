"""Renderer speed against error on a fitted object: the renderer's shortcuts one by one.

Every mode renders the same held-out views of the same fitted field; the time is the median
milliseconds per image over repeats (one process, same threads), the error is PSNR against the
ground-truth views. ``dense`` is the plain renderer: samples spread over the whole scene box, no
occupancy grid, no early termination, colour evaluated at every sample.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from model.data.dataset import load_views
from model.evaluate import composite_over, render_views
from model.fit import load_fit
from model.metrics import psnr
from model.renderer import DENSE, RenderConfig

FAST = RenderConfig()

MODES: dict[str, RenderConfig] = {
    "dense": DENSE,
    "dense-64": replace(DENSE, samples_per_ray=64),
    "occupancy": replace(DENSE, use_occupancy=True),
    "occupancy+termination": replace(FAST, color_weight_threshold=0.0),
    "fast": FAST,
    "fast-64": replace(FAST, samples_per_ray=64),
    "fast-256": replace(FAST, samples_per_ray=256),
    "fast-term1e-2": replace(FAST, termination_threshold=1e-2, color_weight_threshold=1e-3),
}


def run_render_bench(run_dir: Path, *, repeats: int = 3, views: int = 4) -> dict:
    params, grid, cfg, meta = load_fit(run_dir)
    test = load_views(Path(meta["data"]) / meta["object"], split="test")
    test = replace(test, images=test.images[:views], c2w=test.c2w[:views], files=test.files[:views])
    target = composite_over(test.images)
    runs = []
    for mode, render_cfg in MODES.items():
        times = []
        for _ in range(repeats):
            images, ms = render_views(params, cfg.field, test, render_cfg, grid)
            times.append(ms)
        samples = _samples_per_ray(params, cfg.field, test, render_cfg, grid)
        runs.append(
            {
                "mode": mode,
                "ms": float(torch.tensor(times).median()),
                "psnr": sum(psnr(a, b) for a, b in zip(images, target)) / len(images),
                "samples_per_ray": samples,
                "config": render_cfg.to_dict(),
            }
        )
    dense_ms = runs[0]["ms"]
    for run in runs:
        run["speedup_vs_dense"] = dense_ms / run["ms"]
    return {
        "fit": str(run_dir),
        "object": meta.get("object"),
        "resolution": [test.width, test.height],
        "views": views,
        "threads": torch.get_num_threads(),
        "runs": runs,
    }


def _samples_per_ray(params, field_cfg, views, render_cfg, grid) -> float:
    from model.renderer import render_image

    out = render_image(params, field_cfg, views.c2w[0], views.width, views.height, views.focal, render_cfg, grid=grid)
    return float(out["samples"]) / (views.width * views.height)
