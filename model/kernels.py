"""Just-in-time build and lazy loading of the fused C++ CPU kernels in ``model/csrc``.

The kernels are torch C++ extensions compiled with ``torch.utils.cpp_extension.load`` (ninja)
the first time they are needed, never inside pip's isolated build (the extension must match the
torch that runs it). Each build lands in its own folder under the cache
(``$HYPNERF_CACHE`` or ``~/.cache/hypnerf/ext``) named by a hash of everything that changes the
binary: the sources, the compiler flags, the compiler, torch, Python and, because the code is
built with ``-march=native``, the CPU model and its instruction-set flags. Editing a source or
moving the cache to another machine therefore rebuilds instead of loading a stale or
unsupported binary. Later processes load the finished library directly without invoking ninja.

``python -m model.kernels`` builds everything ahead of time.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import platform
import subprocess
import sys
from pathlib import Path

import torch

log = logging.getLogger(__name__)

CSRC = Path(__file__).resolve().parent / "csrc"
# -ffp-contract=off keeps the arithmetic in the same rounding as the PyTorch reference.
CFLAGS = ("-O3", "-march=native", "-fopenmp", "-ffp-contract=off")
LDFLAGS = ("-fopenmp",)
HASHGRID_SOURCES = ("hashgrid.cpp",)
HASHGRID_NAMESPACE = "hypnerf_hashgrid"


def cache_root() -> Path:
    """Folder holding the compiled extensions; ``HYPNERF_CACHE`` overrides the default."""
    root = os.environ.get("HYPNERF_CACHE")
    return Path(root).expanduser() if root else Path.home() / ".cache" / "hypnerf" / "ext"


def _cpu_identity() -> str:
    """CPU model and feature flags: binaries built with -march=native are only valid there."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor() or platform.machine()
    wanted = ("model name", "flags", "Features", "CPU part")
    return "\n".join(sorted({line for line in lines if line.split(":")[0].strip() in wanted}))


@functools.lru_cache(maxsize=None)
def _compiler_identity() -> str:
    cxx = os.environ.get("CXX", "c++")
    try:
        return subprocess.run([cxx, "--version"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return cxx


def build_key(sources: tuple[str, ...]) -> str:
    """Hex digest identifying one binary build of ``sources`` on this machine."""
    h = hashlib.sha256()
    for name in sources:
        h.update(name.encode())
        h.update((CSRC / name).read_bytes())
    for part in (" ".join(CFLAGS), " ".join(LDFLAGS), _compiler_identity(), _cpu_identity(), torch.__version__,
                 sys.version):
        h.update(b"\0" + part.encode())
    return h.hexdigest()[:20]


def _build_or_load(stem: str, sources: tuple[str, ...]) -> Path:
    """Path of the loaded shared library for ``sources``, compiling it first if needed."""
    name = f"{stem}_{build_key(sources)}"
    folder = cache_root() / name
    library = folder / f"{name}.so"
    # A lock file means another process is still compiling into this folder: let load() wait on it.
    if library.exists() and not (folder / "lock").exists():
        torch.ops.load_library(str(library))
        return library
    from torch.utils import cpp_extension

    folder.mkdir(parents=True, exist_ok=True)
    log.warning("compiling the %s C++ extension into %s (first use on this machine; takes a minute)", stem, folder)
    cpp_extension.load(
        name=name,
        sources=[str(CSRC / s) for s in sources],
        extra_cflags=list(CFLAGS),
        extra_ldflags=list(LDFLAGS),
        build_directory=str(folder),
        is_python_module=False,
        verbose=False,
    )
    return library


@functools.lru_cache(maxsize=1)
def hashgrid_ops():
    """The ``torch.ops`` namespace of the fused hash-grid kernel, built on first use.

    Raises whatever the build raised (no compiler, missing headers...); callers decide whether
    to fall back.
    """
    _build_or_load("hashgrid", HASHGRID_SOURCES)
    return getattr(torch.ops, HASHGRID_NAMESPACE)


def main() -> None:
    """Build every extension ahead of time (``python -m model.kernels``)."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    hashgrid_ops()
    log.info("C++ extensions ready in %s", cache_root())


if __name__ == "__main__":
    main()
