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
    "fit": "python -m benchmarks.bench_fit  --objects 4  (runs hypnerf fit per object and mode, 2000 steps; no-masks adds --no-masks)",
    "import": "python -m benchmarks.bench_import  (hypnerf data synth, then hypnerf data import-transforms and hypnerf fit --steps 1500)",
    "presets": "python -m benchmarks.bench_presets",
    "render": "python -m benchmarks.bench_render  (runs: hypnerf bench render --fit runs/bench-fit/masks/<first chair> --json benchmarks/results/render.json)",
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


def _fg(value) -> str:
    return "n/a" if value is None else f"{value:.2f}"


FOREGROUND_NOTE = (
    "Full-image PSNR on a white background flatters, so every quality figure comes with its foreground PSNR "
    "(pixels where the ground truth has alpha > 0 or the render has opacity >= 1/255) and the floor: "
    "the same two figures for a blank white image on the same pixels."
)


def render_section(data: dict) -> list[str]:
    w, h = data["resolution"]
    return [
        "## Renderer: speed against error",
        "",
        f"Object `{data['object']}`, {w}x{h}, {data['views']} held-out views, {data['threads']} threads; "
        "ms is the median per image. The occupancy grid is part of the fitted NeRF (no density in its empty cells). "
        "Each mode adds one shortcut to the one above it: `dense` (128 samples across the scene box, every one evaluated, "
        "colour everywhere, no termination), `dense-tight` (the grid's tight box: same count of samples, finer steps), "
        "`occupancy` (skips empty cells), `+termination` (stops opaque rays), `fast` (shades only samples whose weight "
        "matters). `dense-no-grid` drops the grid from the model to show the haze it removes. Samples/ray counts density "
        "evaluations over all pixels, including rays that miss.",
        "",
        *_table(
            ["mode", "ms / image", "PSNR full (dB)", "PSNR fg (dB)", "full vs dense (dB)", "samples / ray", "speed-up vs dense"],
            [
                [run["mode"], f"{run['ms']:.1f}", f"{run['psnr']:.2f}", _fg(run.get("psnr_fg")), f"{run['psnr_vs_dense']:+.2f}", f"{run['samples_per_ray']:.1f}", f"{run['speedup_vs_dense']:.1f}x"]
                for run in data["runs"]
            ],
        ),
        "",
        f"Blank-image floor on these views: {_fg(data['runs'][0].get('floor_psnr'))} dB full, {_fg(data['runs'][0].get('floor_psnr_fg'))} dB foreground.",
        "",
    ]


def fit_section(data: dict) -> list[str]:
    keys = ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg", "ssim", "chamfer", "wall_s", "samples_per_ray")

    def row(label, mode, m):
        return [label, mode, f"{m['psnr']:.2f}", _fg(m["psnr_fg"]), f"{m['floor_psnr']:.2f} / {_fg(m['floor_psnr_fg'])}",
                f"{m['ssim']:.4f}", _metric(m["chamfer"], ".4f"), f"{m['samples_per_ray']:.1f}", f"{m['wall_s']:.0f}"]

    rows = [row(r["object"], r["mode"], r) for r in data["objects"]]
    rows += [row("**mean**", mode, {k: m[k] for k in keys}) for mode, m in data["mean"].items()]
    masks, free = data["mean"]["masks"], data["mean"]["no-masks"]
    return [
        "## Per-object fits (Sweet Home 3D chairs, 128x128): masks on and off",
        "",
        f"{data['steps']} steps, {data['threads']} threads; held-out views; Chamfer in scene-box units. `masks`: the "
        "occupancy grid starts as the visual hull carved from the training masks; `no-masks`: it starts as every cell a "
        "training view sees and is grown from the field's own density alone (the images keep their alpha as targets). "
        "Samples/ray are those of the held-out renders. " + FOREGROUND_NOTE,
        "",
        *_table(["object", "mode", "PSNR full (dB)", "PSNR fg (dB)", "floor full / fg (dB)", "SSIM", "Chamfer", "samples / ray", "fit wall (s)"], rows),
        "",
        f"Without masks the fits score {free['psnr'] - masks['psnr']:+.2f} dB full and {free['psnr_fg'] - masks['psnr_fg']:+.2f} dB "
        f"foreground against the masked fits and take {free['wall_s'] / masks['wall_s']:.2f}x their time.",
        "",
    ]


def import_section(data: dict) -> list[str]:
    rows = [
        [name, str(r["scene_box"]), f"{r['psnr']:.2f}", f"{r['psnr_fg']:.2f}", f"{r['floor_psnr']:.2f} / {r['floor_psnr_fg']:.2f}", f"{r['ssim']:.4f}", f"{r['wall_s']:.0f}"]
        for name, r in data["rows"].items()
    ]
    return [
        "## A NeRF-synthetic-layout scene through import-transforms",
        "",
        f"{data['scene']}; imported without a box given (box: {data['imported_box_source']}), fitted {data['steps']} steps with masks.",
        "",
        *_table(["scene", "scene box", "PSNR full (dB)", "PSNR fg (dB)", "floor full / fg (dB)", "SSIM", "fit wall (s)"], rows),
        "",
    ]


def _metric(value, fmt: str) -> str:
    return "n/a" if value is None else format(value, fmt)


def training_section(data: dict) -> list[str]:
    lines = [
        "## Category prior: training (Sweet Home 3D chairs with colour variants)",
        "",
        *_table(
            ["preset", "instances (shapes)", "steps", "wall", "rays/s", "samples/s", "samples/ray", "weights", "last validation full / fg / floor fg (dB)", "machine"],
            [
                [
                    run["preset"], f"{run['instances']} ({run['shapes']})", str(run["steps"]), f"{run['wall_s'] / 60:.0f} min", f"{run['rays_per_s']:.0f}",
                    f"{run['samples_per_s'] / 1e6:.2f} M", f"{run['samples_per_ray']:.1f}", f"{run['weights_bytes'] / 1e6:.1f} MB",
                    f"{run['curve'][-1]['val_psnr']:.2f} / {_fg(run['curve'][-1].get('val_psnr_fg'))} / {_fg(run['curve'][-1].get('val_floor_psnr_fg'))}",
                    (f"{run['machine']['cpu']}{'' if run['machine']['avx512'] else ', no AVX-512'}" if "machine" in run else "not recorded"),
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
    h, p = data["hypernet"], data["per_object"]
    lines = [f"## {title}", ""]
    has_fg = h.get("psnr_fg") is not None
    lines += [
        f"{data['objects']} training instances, fixed held-out views at 128x128; per-object fits: {data['per_object_field']} field, "
        f"{data['per_object_steps']} steps. The prior's NeRFs use an occupancy grid from their own density. "
        + (FOREGROUND_NOTE if has_fg else "**Measured before foreground PSNR was reported: no foreground figure or floor is on file for this table; rerun the command below.**"),
        "",
    ]
    labels = (
        (f"prior ({data['field']} field)", h),
        *([(f"prior (hashgrid field, same {data['training_steps']} steps)", data["hypernet_mrhe_same_steps"])] if "hypernet_mrhe_same_steps" in data else []),
        ("per-object fits", p),
    )
    if has_fg:
        lines += _table(
            ["", "PSNR full (dB)", "PSNR fg (dB)", "SSIM", "Chamfer", "render ms"],
            [[label, f"{m['psnr']:.2f}", _fg(m.get("psnr_fg")), f"{m['ssim']:.4f}", _metric(m["chamfer"], ".4f"), _metric(m.get("render_ms"), ".1f")] for label, m in labels],
        )
        lines += ["", f"Blank-image floor: {h['floor_psnr']:.2f} dB full, {_fg(h['floor_psnr_fg'])} dB foreground. "
                  f"PSNR gap **{data['psnr_gap_db']:.2f} dB** full, **{_fg(data.get('psnr_fg_gap_db'))} dB** foreground.", ""]
    else:
        lines += _table(
            ["", "PSNR full (dB)", "SSIM", "Chamfer", "render ms"],
            [[label, f"{m['psnr']:.2f}", f"{m['ssim']:.4f}", _metric(m["chamfer"], ".4f"), _metric(m.get("render_ms"), ".1f")] for label, m in labels],
        )
        lines += ["", f"PSNR gap **{data['psnr_gap_db']:.2f} dB** (full image only).", ""]
    if "hypernet_mrhe_same_steps" in data:
        same = data["hypernet_mrhe_same_steps"]
        lines += [
            f"At equal training steps ({data['training_steps']} each) the hash-grid prior's gap is {same['psnr_gap_db']:.2f} dB, "
            f"so the prior without MRHE scores **{h['psnr'] - same['psnr']:+.2f} dB** against it; the training table and curve "
            "above compare the runs at equal time.",
            "",
        ]
    st = data["storage"]
    if "curve" in st:
        lines += [
            "### Storage at equal precision and equal sharing",
            "",
            f"Counted from parameter counts at {st['weights_dtype']} ({st['method']}). With {st['instances']} instances of {st['shapes']} meshes "
            f"the prior takes {st['prior_bytes'] / 1e6:.1f} MB (file {st['prior_file_bytes'] / 1e6:.1f} MB), per-object fits sharing geometry "
            f"per mesh {st['fits_shared_bytes'] / 1e6:.1f} MB ({st['ratio_fits_shared_to_prior']:.2f}x the prior) and unshared fits "
            f"{st['fits_unshared_bytes'] / 1e6:.1f} MB. **At this size the prior is the larger**: it is a fixed "
            f"{st['per_item']['prior_fixed'] / 1e6:.1f} MB of heads plus {st['per_item']['prior_per_instance'] + st['per_item']['prior_per_shape'] * st['shapes'] / st['instances']:.0f} bytes per instance, "
            f"against {(st['per_item']['fit_per_shape'] * st['shapes'] / st['instances'] + st['per_item']['fit_per_instance']) / 1e3:.1f} kB per instance for shared fits; "
            f"it becomes the smaller from about {st['crossover_instances']:.0f} instances.",
            "",
            *_table(
                ["instances", "prior (MB)", "fits, shared geometry (MB)", "fits, unshared (MB)"],
                [[str(r["instances"]), f"{r['prior_bytes'] / 1e6:.2f}", f"{r['fits_shared_bytes'] / 1e6:.2f}", f"{r['fits_unshared_bytes'] / 1e6:.2f}"] for r in st["curve"]],
            ),
            "",
        ]
    else:
        lines += [
            f"Storage (old report, **without equal sharing**): the prior is {st['prior_bytes'] / 1e6:.1f} MB for {st['prior_instances']} instances; "
            f"unshared per-object fits would take {st['per_object_bytes_for_all_instances'] / 1e6:.1f} MB at the same precision. "
            "Fits sharing geometry per mesh as the prior does would take far less; rerun the command below for the honest curve.",
            "",
        ]
    return lines


def disentanglement_section(data: dict) -> list[str]:
    if "pass_fraction" not in data:
        return [
            "## Shape/colour disentanglement (swapped codes)",
            "",
            f"**Old report, measured before the per-pixel colour metric.** Its geometry figure (Chamfer ratio {_metric(data.get('chamfer_ratio_mean'), '.2f')}x) "
            "holds by construction (density depends on the shape code only) and measures nothing; mean-colour Delta E "
            f"{data['colour_distance_to_color_source_mean']:.1f} to the colour source vs {data['colour_distance_to_shape_source_mean']:.1f} to the shape source.",
            "",
        ]
    return [
        "## Shape/colour disentanglement (swapped codes)",
        "",
        f"{data['pairs']} pairs (A's shape code with B's colour code; different shapes, clearly different colours). "
        f"Geometry: {data['geometry']} (largest density difference found: {data['geometry_max_density_difference']:.1e}); "
        "this is a design fact, not a measurement. What can vary is the colour transfer, measured per pixel "
        f"({data['colour_metric']}):",
        "",
        *_table(
            ["", "Delta E"],
            [
                ["swap vs colour source B (per pixel)", f"{data['colour_error_to_color_source_mean']:.1f}"],
                ["swap vs shape source A (per pixel)", f"{data['colour_error_to_shape_source_mean']:.1f}"],
                ["B's own reconstruction vs B (per pixel, the prior's floor)", f"{data['colour_error_own_reconstruction_mean']:.1f}"],
                ["swap vs B (mean colour only)", f"{data['mean_colour_distance_to_color_source_mean']:.1f}"],
            ],
        ),
        "",
        f"Pairs passing ({data['pass_rule']}): **{data['passed']} of {data['pairs']}**. Renders: `{data['grid_png']}` "
        "(rows: shape source, colour source, swap).",
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
        ("import", import_section),
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
        machine = data.get("machine")
        where = f"{machine['cpu']}, {machine['cores']} cores, hash-grid kernel {'AVX-512' if machine['avx512'] else 'portable (no AVX-512)'}" if machine else "a machine not recorded in the file"
        lines += [f"Command: `{COMMANDS[name]}`; measured on {where}.", ""]
    (ROOT / "BENCHMARKS.md").write_text("\n".join(lines))
    print("wrote BENCHMARKS.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
