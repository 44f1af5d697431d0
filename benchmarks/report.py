"""Write BENCHMARKS.md from the JSON files under benchmarks/results/ (the latest figures only)."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.common import RESULTS, ROOT

COMMANDS = {
    "encoding": "make bench  (or: python -m benchmarks.bench_encoding)",
    "fit": "python -m benchmarks.bench_fit  (runs hypnerf fit per object, 6 objects, 2000 steps)",
    "render": "python -m benchmarks.bench_render  (runs: hypnerf bench render --fit runs/bench-fit/<first chair> --json benchmarks/results/render.json)",
}


def _load(name: str) -> dict | None:
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def encoding_section(data: dict) -> list[str]:
    cfg = data["config"]
    lines = [
        "## Hash encoding vs nerfstudio's torch HashEncoding",
        "",
        f"L={cfg.get('levels')}, T=2^{cfg.get('log2_table_size')}, F={cfg.get('features')}, "
        f"{data.get('points', 'N')} points, {data['threads']} threads, one process, medians.",
        "",
        "| implementation | pass | M points/s |",
        "|---|---|---|",
    ]
    for run in data["runs"]:
        lines.append(f"| {run['impl']} | {run['pass']} | {run['points_per_s'] / 1e6:.2f} |")
    speed = data["speedup_vs_nerfstudio"]
    lines += ["", f"Speed-up over nerfstudio: **{speed['forward']:.0f}x forward, {speed['forward+backward']:.0f}x forward+backward**.", ""]
    return lines


def render_section(data: dict) -> list[str]:
    w, h = data["resolution"]
    lines = [
        "## Renderer: speed against error",
        "",
        f"Object `{data['object']}`, {w}x{h}, {data['views']} held-out views, {data['threads']} threads; "
        "ms is the median per image, PSNR against the ground truth. The occupancy grid is part of the "
        "fitted NeRF (no density in its empty cells); `dense` renders that NeRF without shortcuts "
        "(128 samples across the scene box, every one evaluated, colour everywhere, no termination), "
        "`dense-no-grid` drops the grid from the model to show the haze it removes.",
        "",
        "| mode | ms / image | PSNR (dB) | PSNR vs dense (dB) | samples / ray | speed-up vs dense |",
        "|---|---|---|---|---|---|",
    ]
    for run in data["runs"]:
        lines.append(
            f"| {run['mode']} | {run['ms']:.1f} | {run['psnr']:.2f} | {run['psnr_vs_dense']:+.2f} | "
            f"{run['samples_per_ray']:.1f} | {run['speedup_vs_dense']:.1f}x |"
        )
    return lines + [""]


def fit_section(data: dict) -> list[str]:
    lines = [
        "## Per-object fits (Sweet Home 3D chairs, 128x128)",
        "",
        f"{data['steps']} steps, {data['threads']} threads; PSNR/SSIM on the fixed held-out views; Chamfer in scene-box units.",
        "",
        *([data["note"], ""] if data.get("note") else []),
        "| object | PSNR (dB) | SSIM | Chamfer | fit wall (s) |",
        "|---|---|---|---|---|",
    ]
    for row in data["objects"]:
        lines.append(f"| {row['object']} | {row['psnr']:.2f} | {row['ssim']:.4f} | {row['chamfer']:.4f} | {row['wall_s']:.0f} |")
    m = data["mean"]
    lines.append(f"| **mean** | **{m['psnr']:.2f}** | **{m['ssim']:.4f}** | **{m['chamfer']:.4f}** | **{m['wall_s']:.0f}** |")
    return lines + [""]


def main() -> int:
    lines = [
        "# Benchmarks",
        "",
        "Latest figures, written by `python -m benchmarks.report` from `benchmarks/results/*.json`. "
        "Machine: 2 CPU cores, 24 GiB. Speeds compare runs within one process only.",
        "",
    ]
    for name, section in (("encoding", encoding_section), ("render", render_section), ("fit", fit_section)):
        data = _load(name)
        if data is None:
            continue
        lines += section(data)
        lines += [f"Command: `{COMMANDS[name]}`", ""]
    (ROOT / "BENCHMARKS.md").write_text("\n".join(lines))
    print("wrote BENCHMARKS.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
