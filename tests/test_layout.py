"""The package layout keeps its promises: imports run one way, the CLI starts light, configs
round-trip through one helper, and both field kinds implement the field protocol."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from model.nerf import config
from model.nerf.fields import Field, FieldConfig, PEFieldConfig
from model.nerf.occupancy import OccupancyConfig
from model.optimize.fit import FitConfig

ROOT = Path(__file__).resolve().parents[1]

# model/ subpackages from the bottom up: a package may import only packages of lower or equal rank
RANKS = {"nerf": 0, "data": 1, "prior": 2, "optimize": 3, "denoise": 4, "eval": 5, "train": 6, "bundle": 7, "cli": 8}
SERVICE_FORBIDDEN = ("model.train", "model.eval", "model.cli", "model.data.build", "model.data.synth", "model.data.sh3d",
                     "model.data.imports", "model.data.transforms", "model.data.raycast")


def _imports(path: Path) -> list[str]:
    """Absolute module names imported by a file, including imports inside functions."""
    names = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def _package_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "model" else None


def layering_violations(root: Path) -> list[str]:
    problems = []
    for path in sorted((root / "model").rglob("*.py")):
        parts = path.relative_to(root / "model").parts
        if len(parts) == 1 and parts[0] == "__init__.py":
            continue
        own = parts[0]
        if own not in RANKS:
            problems.append(f"{path.relative_to(root)}: model/{own} is not a known layer; add it to RANKS")
            continue
        for name in _imports(path):
            other = _package_of(name)
            if other in RANKS and RANKS[other] > RANKS[own]:
                problems.append(f"{path.relative_to(root)} (model/{own}) imports {name} (model/{other}, a higher layer)")
    for path in sorted((root / "service").rglob("*.py")):
        problems += [f"{path.relative_to(root)} imports {name}" for name in _imports(path) if name.startswith(SERVICE_FORBIDDEN)]
    # only the command line (``hypnerf serve``) may start the service: the model never depends on it
    for path in sorted((root / "model").rglob("*.py")):
        if path.relative_to(root / "model").parts[0] != "cli":
            problems += [f"{path.relative_to(root)} imports {name}" for name in _imports(path) if name.split(".")[0] == "service"]
    for path in sorted((root / "clients").rglob("*.py")):
        problems += [f"{path.relative_to(root)} imports {name}" for name in _imports(path) if name.split(".")[0] in ("model", "service")]
    return problems


def test_imports_run_one_way():
    assert layering_violations(ROOT) == []


def test_the_layering_check_catches_an_upward_import(tmp_path):
    (tmp_path / "model" / "nerf").mkdir(parents=True)
    (tmp_path / "model" / "nerf" / "bad.py").write_text("def f():\n    from model.train.prior import train\n")
    (tmp_path / "clients").mkdir()
    (tmp_path / "clients" / "sdk.py").write_text("import model.nerf\n")
    (tmp_path / "service").mkdir()
    (tmp_path / "service" / "app.py").write_text("from model.eval.prior import compression\n")
    problems = layering_violations(tmp_path)
    assert len(problems) == 3 and "higher layer" in problems[0]


def test_help_does_not_import_torch():
    code = "import sys; from model.cli.main import build_parser; build_parser(['--help']).format_help(); print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"
    shown = subprocess.run([sys.executable, "-m", "model.cli", "--help"], cwd=ROOT, capture_output=True, text=True)
    assert shown.returncode == 0 and "import-transforms" not in shown.stdout and "train" in shown.stdout


def test_configs_round_trip_through_json():
    fit = FitConfig(field=PEFieldConfig(), steps=7, betas=(0.8, 0.9), occupancy=OccupancyConfig(resolution=16))
    data = json.loads(json.dumps(config.to_dict(fit)))
    assert data["field"]["kind"] == "positional" and data["betas"] == [0.8, 0.9]
    back = config.from_dict(FitConfig, data)
    assert back == fit and isinstance(back.field, PEFieldConfig) and back.betas == (0.8, 0.9)
    assert isinstance(config.from_dict(FitConfig, {}).field, FieldConfig)  # missing keys take defaults


def test_config_errors_name_the_problem():
    with pytest.raises(ValueError, match="unknown FitConfig settings \\['stepz'\\]"):
        config.from_dict(FitConfig, {"stepz": 3})
    with pytest.raises(ValueError, match="unknown field kind"):
        config.from_dict(FitConfig, {"field": {"kind": "voxels"}})

    @dataclass
    class Nested:
        values: tuple[int, ...] = (1, 2)
        maybe: OccupancyConfig | None = None
        tags: dict = field(default_factory=dict)

    assert config.from_dict(Nested, {"values": [3, 4, 5], "maybe": {"resolution": 8}}) == Nested((3, 4, 5), OccupancyConfig(resolution=8))


def test_both_field_kinds_implement_the_protocol():
    for kind in (FieldConfig(), PEFieldConfig()):
        assert isinstance(kind, Field), type(kind).__name__
