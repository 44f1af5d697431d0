"""Shared pieces of the benchmark scripts: paths, running the CLI, writing results."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
SH3D_CHAIRS = ROOT / "data" / "sh3d-chair-bench"


def hypnerf(*args: str) -> None:
    """Run the ``hypnerf`` CLI in a fresh process (its own allocator settings, clean timings)."""
    subprocess.run([sys.executable, "-m", "model.cli", *args], check=True, cwd=ROOT, env=os.environ.copy())


def ensure_sh3d_chairs(count: int = 6, res: int = 128) -> Path:
    """The benchmark's real chairs: ``count`` Sweet Home 3D chairs spread over the category list."""
    if not (SH3D_CHAIRS / "index.json").is_file():
        hypnerf("data", "import-sh3d", "--out", str(SH3D_CHAIRS), "--category", "chair", "--views", "91", "--res", str(res), "--limit", str(count))
    return SH3D_CHAIRS


def write_result(name: str, payload: dict) -> Path:
    from model.nerf.encodings.kernels import machine_summary

    payload = {**payload, "machine": payload.get("machine", machine_summary())}
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {path.relative_to(ROOT)}")
    return path
