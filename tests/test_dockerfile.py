"""What can be checked of the Dockerfile without a Docker daemon: it is multi-stage; every file it
copies exists and is in the build context (``.dockerignore``); the command it runs is the project's
console script with flags that parse; the healthcheck probes a real route with code that compiles;
it runs as a non-root user; torch is the project's pin from PyTorch's CPU index; every ``HYPNERF_*``
variable it sets is a setting the service reads, and together they make valid settings.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def instructions(text: str) -> list[tuple[str, str]]:
    """The Dockerfile as (INSTRUCTION, arguments), continuation lines joined, comments dropped."""
    logical, pending = [], ""
    for line in text.splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if stripped.startswith("#"):
            continue
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        logical.append(pending + stripped)
        pending = ""
    return [(line.split(None, 1)[0].upper(), line.split(None, 1)[1] if " " in line else "") for line in logical]


def stages(steps: list[tuple[str, str]]) -> dict[str, list[tuple[str, str]]]:
    """Instructions by stage name (``FROM image AS name``; unnamed stages by index)."""
    found: dict[str, list[tuple[str, str]]] = {}
    current = None
    for name, args in steps:
        if name == "FROM":
            words = args.split()
            current = words[2].lower() if len(words) >= 3 and words[1].lower() == "as" else str(len(found))
            found[current] = []
        elif current is not None:
            found[current].append((name, args))
    return found


def copy_parts(args: str) -> tuple[dict[str, str], list[str], str]:
    """``COPY [--flag=value ...] SRC... DEST`` -> (flags, sources, destination)."""
    words = shlex.split(args)
    flags = dict(word[2:].split("=", 1) for word in words if word.startswith("--"))
    paths = [word for word in words if not word.startswith("--")]
    return flags, paths[:-1], paths[-1]


def _pattern(pattern: str) -> re.Pattern:
    """A ``.dockerignore`` pattern as a regex (Go filepath.Match plus ``**`` for any directories)."""
    out, i = "", 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pattern.startswith("**", i):
            out, i = out + ".*", i + 2
        elif pattern[i] == "*":
            out, i = out + "[^/]*", i + 1
        elif pattern[i] == "?":
            out, i = out + "[^/]", i + 1
        else:
            out, i = out + re.escape(pattern[i]), i + 1
    return re.compile(out + r"\Z")


def ignore_rules(text: str) -> list[tuple[bool, re.Pattern]]:
    rules = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        keep = line.startswith("!")
        rules.append((keep, _pattern(line.lstrip("!").strip().strip("/").removeprefix("./"))))
    return rules


def ignored(path: str, rules: list[tuple[bool, re.Pattern]]) -> bool:
    """Whether the build context leaves ``path`` out: as Docker does, a rule applies when it matches
    the path or one of its parent folders, and the last rule that applies wins."""
    parts = path.split("/")
    prefixes = ["/".join(parts[:n]) for n in range(1, len(parts) + 1)]
    excluded = False
    for keep, pattern in rules:
        if any(pattern.match(prefix) for prefix in prefixes):
            excluded = not keep
    return excluded


@pytest.fixture(scope="module")
def dockerfile() -> list[tuple[str, str]]:
    return instructions((ROOT / "Dockerfile").read_text())


@pytest.fixture(scope="module")
def rules() -> list[tuple[bool, re.Pattern]]:
    return ignore_rules((ROOT / ".dockerignore").read_text())


def _last(steps: list[tuple[str, str]], name: str) -> str:
    found = [args for step, args in steps if step == name]
    assert found, f"the Dockerfile has no {name}"
    return found[-1]


def _env(steps: list[tuple[str, str]]) -> dict[str, str]:
    values = {}
    for name, args in steps:
        if name == "ENV":
            values.update(word.split("=", 1) for word in shlex.split(args))
    return values


def test_it_is_multi_stage_from_python_slim(dockerfile):
    found = stages(dockerfile)
    assert next(iter(found)) == "builder" and len(found) >= 2
    args = {k: v for k, v in (a.split("=", 1) for step, a in dockerfile if step == "ARG" and "=" in a)}
    images = [args.get(a.split()[0].strip("${}"), a.split()[0]) for step, a in dockerfile if step == "FROM"]
    assert all(image.startswith("python:3.11-slim") for image in images), images


def test_every_copied_file_exists_and_is_in_the_build_context(dockerfile, rules):
    found = stages(dockerfile)
    builder_text = " ".join(args for _, args in found["builder"])
    for name, args in dockerfile:
        if name != "COPY":
            continue
        flags, sources, _ = copy_parts(args)
        if "from" in flags:  # made by an earlier stage: it must be created there
            assert all(source in builder_text for source in sources), args
            continue
        for source in sources:
            path = ROOT / source
            assert path.exists(), f"COPY {source}: not in the repository"
            files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
            sent = [p for p in files if not ignored(p.relative_to(ROOT).as_posix(), rules)]
            assert sent, f"COPY {source}: .dockerignore leaves all of it out of the build context"
            assert not any("__pycache__" in p.parts for p in sent)


def test_the_build_context_leaves_out_local_state(rules):
    for path in (".venv/bin/python", "runs/prior-cpu/prior.json", "data/x/index.json", ".git/HEAD", "tests/test_client.py",
                 "model/__pycache__/x.pyc", "bundles/other/manifest.json"):
        assert ignored(path, rules), path
    for path in ("pyproject.toml", "model/nerf/encodings/csrc/hashgrid.cpp", "service/app.py", "clients/python/pyproject.toml",
                 "bundles/chair-demo/manifest.json"):
        assert not ignored(path, rules), path


def test_the_command_is_the_console_script_with_flags_that_parse(dockerfile):
    argv = json.loads(_last(dockerfile, "CMD"))
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert argv[0] in scripts and scripts[argv[0]] == "model.cli.main:main"
    from model.cli.main import build_parser
    from model.cli.serve import cmd_serve

    args = build_parser(argv[1:]).parse_args(argv[1:])
    assert args.command == "serve" and args.func is cmd_serve
    shown = subprocess.run([sys.executable, "-m", "model.cli", *argv[1:2], "--help"], cwd=ROOT, capture_output=True, text=True, check=True)
    assert all(flag in shown.stdout for flag in argv[2:] if flag.startswith("--"))
    # the bundle it serves is the one copied in
    copied = [copy_parts(a)[2].rstrip("/") for step, a in dockerfile if step == "COPY" and "bundles/chair-demo" in copy_parts(a)[1]]
    assert copied == [args.bundle] == [_env(dockerfile)["HYPNERF_BUNDLE"]]


def test_the_healthcheck_probes_readiness_on_a_real_route(dockerfile, tmp_path):
    check = _last(dockerfile, "HEALTHCHECK")
    command = shlex.split(check.split(" CMD ", 1)[1])
    assert command[:2] == ["python", "-c"] and "/readyz" in command[2]
    compile(command[2], "HEALTHCHECK", "exec")
    from service.app import create_app
    from service.settings import Settings

    paths = create_app(Settings(state_dir=tmp_path)).openapi()["paths"]  # built without starting the app
    assert "get" in paths["/readyz"]
    assert _env(dockerfile)["HYPNERF_PORT"] == _last(dockerfile, "EXPOSE") == "8000"


def test_it_runs_as_a_non_root_user(dockerfile):
    runtime = list(stages(dockerfile).values())[-1]
    user = _last(runtime, "USER")
    assert user not in ("root", "0") and not user.startswith(("root:", "0:"))
    assert any(step == "RUN" and re.search(rf"useradd\b.*\b{re.escape(user)}\b", args) for step, args in runtime)


def test_torch_is_the_project_pin_from_the_cpu_index(dockerfile):
    pins = [d for d in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"] if d.startswith("torch")]
    assert len(pins) == 1 and pins[0].startswith("torch==")
    installs = [args for step, args in dockerfile if step == "RUN" and "torch==" in args]
    assert len(installs) == 1 and re.search(rf"{re.escape(pins[0])}\s", installs[0] + " ") and f"--index-url {CPU_INDEX}" in installs[0]


def test_its_settings_are_ones_the_service_reads(dockerfile, monkeypatch, tmp_path):
    from model.nerf.encodings import kernels
    from service.settings import Settings

    env = {name: value for name, value in _env(dockerfile).items() if name.startswith("HYPNERF_")}
    for name in env:
        field = name.removeprefix("HYPNERF_").lower().split("__")[0]
        assert field in Settings.model_fields or name == "HYPNERF_CACHE", f"{name} is not a setting"
    monkeypatch.setenv("HYPNERF_CACHE", str(tmp_path))
    assert kernels.cache_root() == tmp_path  # the kernel cache the image fills
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    monkeypatch.delenv("HYPNERF_API_KEYS", raising=False)
    with pytest.raises(ValueError, match="HYPNERF_API_KEYS"):  # bound to 0.0.0.0: keys are required
        Settings()
    monkeypatch.setenv("HYPNERF_API_KEYS", "a-key")
    settings = Settings()
    assert settings.host == "0.0.0.0" and str(settings.bundle) == env["HYPNERF_BUNDLE"] and settings.port == 8000
