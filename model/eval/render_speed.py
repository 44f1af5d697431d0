"""Renderer speed against error on a fitted object: the renderer's shortcuts one by one.

Every mode renders the same held-out views of the same fitted NeRF; the time is the median
milliseconds per image over repeats (one process, same threads), the error is PSNR against the
ground-truth views.

The occupancy grid is part of a fitted NeRF, as in InstantNGP: its empty cells hold no density.
``dense`` is the reference renderer of that model: samples spread over the whole scene box, the
field evaluated at every one of them (density then zeroed in empty cells), no early termination,
colour at every sample. Each further mode adds one shortcut, so the table separates them:
``dense-tight`` marches the grid's tight box (same sample count, finer steps), ``occupancy`` also
skips empty cells, ``+termination`` stops rays once opaque, ``fast`` also shades only samples
whose weight matters. ``dense-no-grid`` drops the grid from the model to show what it removes
(haze where no training ray ever looked). Quality is full-image and foreground PSNR.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from model.data.dataset import load_views
from model.nerf import config
from model.nerf.encodings.kernels import machine_summary
from model.eval.field import render_views
from model.eval.metrics import image_quality
from model.nerf.renderer import DENSE, DENSE_TIGHT, RenderConfig
from model.optimize.fit import load_fit

FAST = RenderConfig()

# mode -> (render settings, whether the NeRF keeps its occupancy grid)
MODES: dict[str, tuple[RenderConfig, bool]] = {
    "dense": (DENSE, True),
    "dense-64": (replace(DENSE, samples_per_ray=64), True),
    "dense-no-grid": (DENSE, False),
    "dense-tight": (DENSE_TIGHT, True),
    "occupancy": (replace(DENSE_TIGHT, skip_empty=True), True),
    "occupancy+termination": (replace(FAST, color_weight_threshold=0.0), True),
    "fast": (FAST, True),
    "fast-64": (replace(FAST, samples_per_ray=64), True),
    "fast-256": (replace(FAST, samples_per_ray=256), True),
    "fast-term1e-2": (replace(FAST, termination_threshold=1e-2, color_weight_threshold=1e-3), True),
}


def run_render_bench(run_dir: Path, *, repeats: int = 3, views: int = 4) -> dict:
    params, grid, scene, cfg, meta = load_fit(run_dir)
    test = load_views(Path(meta["data"]) / meta["object"], split="test").subset(slice(0, views))
    runs = []
    for mode, (render_cfg, with_grid) in MODES.items():
        times = []
        for _ in range(repeats):
            images, opacity, ms, samples_per_ray = render_views(params, cfg.field, test, render_cfg, grid if with_grid else None, scene)
            times.append(ms)
        quality = image_quality(images, test.images, opacity, render_cfg.background)
        runs.append(
            {
                "mode": mode,
                "ms": float(torch.tensor(times).median()),
                **{k: quality[k] for k in ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg")},
                "samples_per_ray": samples_per_ray,
                "occupancy_grid": with_grid,
                "config": config.to_dict(render_cfg),
            }
        )
    dense = runs[0]
    for run in runs:
        run["speedup_vs_dense"] = dense["ms"] / run["ms"]
        run["psnr_vs_dense"] = run["psnr"] - dense["psnr"]
    return {
        "fit": str(run_dir),
        "object": meta.get("object"),
        "resolution": [test.width, test.height],
        "views": views,
        "threads": torch.get_num_threads(),
        "machine": machine_summary(),
        "runs": runs,
    }
