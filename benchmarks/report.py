"""Write BENCHMARKS.md from the JSON files under benchmarks/results/ (the latest figures only)."""

from __future__ import annotations

import json

from benchmarks.common import RESULTS, ROOT

COMMANDS = {
    "training": "make bench-prior  (or: python -m benchmarks.bench_prior; its training stage runs the hypnerf train command shown in the table)",
    "compression": "hypnerf eval compression --run runs/prior-cpu --data data/sh3d-chair-variants --json benchmarks/results/compression.json --objects 10 --fits runs/prior-fits --fit-steps 2000",
    "compression_no_mrhe": "hypnerf eval compression --run runs/prior-no-mrhe --data data/sh3d-chair-variants --json benchmarks/results/compression_no_mrhe.json --objects 10 --fits runs/prior-fits --fit-steps 2000 --ablation no-mrhe",
    "disentanglement": "hypnerf eval disentanglement --run runs/prior-cpu --data data/sh3d-chair-variants --json benchmarks/results/disentanglement.json --pairs 10",
    "encoding": "make bench  (or: python -m benchmarks.bench_encoding)",
    "fit": "python -m benchmarks.bench_fit  (runs hypnerf fit per object, 6 objects, 2000 steps)",
    "presets": "python -m benchmarks.bench_presets",
    "render": "python -m benchmarks.bench_render  (runs: hypnerf bench render --fit runs/bench-fit/<first chair> --json benchmarks/results/render.json)",
}


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A markdown table: a header row, its rule, one line per row."""
    return [f"| {' | '.join(header)} |", "|" + "---|" * len(header), *(f"| {' | '.join(row)} |" for row in rows)]


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
        *_table(["implementation", "pass", "M points/s"], [[run["impl"], run["pass"], f"{run['points_per_s'] / 1e6:.2f}"] for run in data["runs"]]),
    ]
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
        *_table(
            ["mode", "ms / image", "PSNR (dB)", "PSNR vs dense (dB)", "samples / ray", "speed-up vs dense"],
            [
                [run["mode"], f"{run['ms']:.1f}", f"{run['psnr']:.2f}", f"{run['psnr_vs_dense']:+.2f}", f"{run['samples_per_ray']:.1f}", f"{run['speedup_vs_dense']:.1f}x"]
                for run in data["runs"]
            ],
        ),
    ]
    return lines + [""]


def fit_section(data: dict) -> list[str]:
    m = data["mean"]
    rows = [[row["object"], f"{row['psnr']:.2f}", f"{row['ssim']:.4f}", f"{row['chamfer']:.4f}", f"{row['wall_s']:.0f}"] for row in data["objects"]]
    rows.append(["**mean**", f"**{m['psnr']:.2f}**", f"**{m['ssim']:.4f}**", f"**{m['chamfer']:.4f}**", f"**{m['wall_s']:.0f}**"])
    return [
        "## Per-object fits (Sweet Home 3D chairs, 128x128)",
        "",
        f"{data['steps']} steps, {data['threads']} threads; PSNR/SSIM on the fixed held-out views; Chamfer in scene-box units.",
        "",
        *([data["note"], ""] if data.get("note") else []),
        *_table(["object", "PSNR (dB)", "SSIM", "Chamfer", "fit wall (s)"], rows),
        "",
    ]


def _metric(value, fmt: str) -> str:
    return "n/a" if value is None else format(value, fmt)


def training_section(data: dict) -> list[str]:
    lines = [
        "## Category prior: training (Sweet Home 3D chairs with colour variants)",
        "",
        *_table(
            ["preset", "instances (shapes)", "steps", "wall", "rays/s", "samples/s", "samples/ray", "weights"],
            [
                [
                    run["preset"], f"{run['instances']} ({run['shapes']})", str(run["steps"]), f"{run['wall_s'] / 60:.0f} min", f"{run['rays_per_s']:.0f}",
                    f"{run['samples_per_s'] / 1e6:.2f} M", f"{run['samples_per_ray']:.1f}", f"{run['weights_bytes'] / 1e6:.1f} MB",
                ]
                for run in data["runs"]
            ],
        ),
    ]
    lines += ["", "Hypernetwork parameters per head:", ""]
    for run in data["runs"]:
        counts = ", ".join(f"{k} {v:,}" for k, v in run["parameters"].items())
        lines.append(f"- {run['preset']}: {counts} (total {sum(run['parameters'].values()):,})")
    lines += ["", f"![held-out PSNR against training time]({data['curve_png']})", ""]
    return lines


def presets_section(data: dict) -> list[str]:
    return [
        "## Hypernetwork presets: size, speed, quality",
        "",
        f"Each preset trained {data['steps']} steps on the first {data['instances']} instances of the train split "
        f"({data['objects_per_step']} objects x {data['rays_per_step'] // data['objects_per_step']} rays per step), scored on one "
        f"held-out view of every instance; rays/s from a short run after warm-up, {data['threads']} threads. "
        "Weights are the exported fp16 prior (the demo bundle allows 30 MB).",
        "",
        *_table(
            ["preset", "codes", "heads", "table head", "parameters", "weights", "rays/s", "held-out PSNR (dB)"],
            [
                [
                    run["preset"], f"{run['shape_code_dim']} + {run['color_code_dim']}", f"{run['head_layers']} x {run['head_hidden']}",
                    "full rank" if run["table_rank"] is None else f"rank {run['table_rank']}", f"{run['parameters'] / 1e6:.1f} M",
                    f"{run['weights_bytes'] / 1e6:.1f} MB", f"{run['rays_per_s']:.0f}", f"{run['held_out_psnr']:.2f}",
                ]
                for run in data["runs"]
            ],
        ),
        "",
        "Where training rays take samples (the cpu preset, same runs and scoring): the visual hull carved from the masks, "
        "a band one cell around the ground-truth surface, or the whole box.",
        "",
        *_table(
            ["training occupancy", "samples / ray", "rays/s", "held-out PSNR (dB)"],
            [[run["occupancy"], f"{run['samples_per_ray']:.1f}", f"{run['rays_per_s']:.0f}", f"{run['held_out_psnr']:.2f}"] for run in data.get("occupancy", [])],
        ),
        "",
    ]


def compression_section(data: dict, title: str) -> list[str]:
    h, p, st = data["hypernet"], data["per_object"], data["storage"]
    lines = [
        f"## {title}",
        "",
        f"{data['objects']} training instances, fixed held-out views at 128x128; per-object fits: {data['per_object_field']} field, "
        f"{data['per_object_steps']} steps. The prior's NeRFs use an occupancy grid from their own density.",
        "",
        *_table(
            ["", "PSNR (dB)", "SSIM", "Chamfer", "render ms"],
            [
                [label, f"{m['psnr']:.2f}", f"{m['ssim']:.4f}", _metric(m["chamfer"], ".4f"), _metric(m.get("render_ms"), ".1f")]
                for label, m in (
                    (f"prior ({data['field']} field)", h),
                    *([(f"prior (hashgrid field, same {data['training_steps']} steps)", data["hypernet_mrhe_same_steps"])] if "hypernet_mrhe_same_steps" in data else []),
                    ("per-object fits", p),
                )
            ],
        ),
        "",
        f"PSNR gap **{data['psnr_gap_db']:.2f} dB**. Storage: the prior is {st['prior_bytes'] / 1e6:.1f} MB for {st['prior_instances']} instances; "
        f"per-object fits of {st['per_object_parameters']:,} parameters each would take {st['per_object_bytes_for_all_instances'] / 1e6:.1f} MB "
        f"at the same precision ({st['weights_dtype']}), {st['compression_ratio']:.2f}x the prior's size.",
        "",
    ]
    if "hypernet_mrhe_same_steps" in data:
        same = data["hypernet_mrhe_same_steps"]
        lines += [
            f"At equal training steps ({data['training_steps']} each) the hash-grid prior's gap is {same['psnr_gap_db']:.2f} dB, "
            f"so the prior without MRHE scores **{h['psnr'] - same['psnr']:+.2f} dB** against it; the training table and curve "
            "above compare the runs at equal time.",
            "",
        ]
    return lines


def disentanglement_section(data: dict) -> list[str]:
    return [
        "## Shape/colour disentanglement (swapped codes)",
        "",
        f"{data['pairs']} pairs (A's shape code with B's colour code; different shapes, clearly different colours). "
        f"Chamfer of the swapped NeRF's mesh to A's ground truth relative to A's own reconstruction: "
        f"mean **{_metric(data['chamfer_ratio_mean'], '.2f')}x**, max {_metric(data['chamfer_ratio_max'], '.2f')}x. "
        f"Colour ({data['colour_metric']}): {data['colour_distance_to_color_source_mean']:.1f} to B (the colour source) vs "
        f"{data['colour_distance_to_shape_source_mean']:.1f} to A; closer to B in {data['colour_closer_to_color_source']} of {data['pairs']} pairs.",
        "",
    ]


def main() -> int:
    lines = [
        "# Benchmarks",
        "",
        "Latest figures, written by `python -m benchmarks.report` from `benchmarks/results/*.json`. "
        "Machine: 2 CPU cores, 24 GiB. Speeds compare runs within one process only.",
        "",
    ]
    sections = (
        ("encoding", encoding_section),
        ("render", render_section),
        ("fit", fit_section),
        ("presets", presets_section),
        ("training", training_section),
        ("compression", lambda d: compression_section(d, "Compression: prior vs per-object fits (paper Table 2)")),
        ("compression_no_mrhe", lambda d: compression_section(d, "Ablation without MRHE (paper Table 4)")),
        ("disentanglement", disentanglement_section),
    )
    for name, section in sections:
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
