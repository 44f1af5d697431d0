"""A scene in the NeRF-synthetic convention, imported with ``hypnerf data import-transforms`` and fitted.

A procedural chair is rendered at 200x200 (100 training views, 12 held-out views) in this
project's unit box, then written again in the NeRF-synthetic layout at three times the scale
(camera positions x3, so the object lies within [-1.5, 1.5]^3 and cameras at radius 6; files
``transforms_train.json`` / ``transforms_test.json`` with ``file_path`` without extension), imported
(no box given: the convention's is taken) and fitted. The same chair fitted in its unit box is
the reference: with the scene box taken from the data the two should agree.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from benchmarks.common import ROOT, hypnerf, write_result

RUNS = ROOT / "runs" / "bench-import"
STEPS = 1500


def write_nerf_synthetic(object_dir: Path, target: Path, scale: float) -> None:
    transforms = json.loads((object_dir / "transforms.json").read_text())
    for split in ("train", "test"):
        frames = []
        for frame in transforms["frames"]:
            if frame["split"] != split:
                continue
            name = f"{split}/r_{len(frames)}"
            (target / split).mkdir(parents=True, exist_ok=True)
            shutil.copy(object_dir / frame["file_path"], target / f"{name}.png")
            pose = [row[:] for row in frame["transform_matrix"]]
            for row in pose[:3]:
                row[3] *= scale
            frames.append({"file_path": f"./{name}", "rotation": 0.0, "transform_matrix": pose})
        (target / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": transforms["camera_angle_x"], "frames": frames}, indent=1))


def main() -> int:
    synth = RUNS / "synth"
    if not (synth / "index.json").is_file():
        hypnerf("data", "synth", "--out", str(synth), "--objects", "1", "--views", "100", "--res", "200", "--seed", "0")
    object_id = json.loads((synth / "index.json").read_text())["objects"][0]["id"]
    source = RUNS / "nerf-synthetic" / "chair"
    if not (source / "transforms_train.json").is_file():
        write_nerf_synthetic(synth / object_id, source, 3.0)
    imported = RUNS / "imported"
    hypnerf("data", "import-transforms", str(source), "--out", str(imported))
    rows = {}
    for name, data, obj in (("unit box (as rendered)", synth, object_id), ("NeRF-synthetic x3, imported", imported, "chair")):
        out = RUNS / "fits" / ("unit" if data == synth else "imported")
        hypnerf("fit", "--data", str(data), "--object", obj, "--out", str(out), "--steps", str(STEPS))
        m = json.loads((out / "metrics.json").read_text())
        box = json.loads((out / "config.json").read_text())["scene_box"]
        rows[name] = {"scene_box": box, **{k: m[k] for k in ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg", "ssim", "wall_s", "samples_per_ray")}}
        print(f"{name}: {m['psnr']:.2f} dB full, {m['psnr_fg']:.2f} dB foreground (floors {m['floor_psnr']:.2f} / {m['floor_psnr_fg']:.2f}), {m['wall_s']:.0f} s")
    source_box = json.loads((imported / "chair" / "transforms.json").read_text())["source"]["aabb_source"]
    write_result(
        "import",
        {
            "command": "python -m benchmarks.bench_import",
            "scene": "procedural chair (synth seed 0), 100 training + 12 held-out views at 200x200; written in the NeRF-synthetic layout at scale 3",
            "steps": STEPS,
            "imported_box_source": source_box,
            "rows": rows,
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
