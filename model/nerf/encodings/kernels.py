"""Just-in-time build and lazy loading of the fused C++ CPU kernels in ``model/csrc``.

The kernels are torch C++ extensions compiled with ``torch.utils.cpp_extension.load`` (ninja)
the first time they are needed, never inside pip's isolated build: the binary must match the
torch that runs it. Each build lands in the cache (``$HYPNERF_CACHE`` or ``~/.cache/hypnerf/ext``)
under a name keyed by a hash of everything that changes the binary: every file in ``model/csrc``,
the compiler flags, the compiler, torch, Python and, because the code is built with
``-march=native``, the CPU model and its instruction-set flags. Editing a source, or reaching the
same cache from another machine, therefore rebuilds instead of loading a stale or unsupported
binary. A build happens in a private folder and the finished library is moved into place
atomically, so concurrent processes never see a half-written file; later processes load it
directly without running ninja. Loading a library marks it used (its mtime); after each new
build, other builds of the same extension unused for ``STALE_AFTER_DAYS`` are deleted, so
edits and upgrades do not pile up binaries while a cache shared by other machines keeps theirs.

``python -m model.nerf.encodings.kernels`` builds everything ahead of time.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

log = logging.getLogger(__name__)

CSRC = Path(__file__).resolve().parent / "csrc"
# -ffp-contract=off: a fused x * res - cell would compute the cell fraction from an unrounded
# product, which can disagree with the cell chosen from the rounded one (and with the reference).
CFLAGS = ("-O3", "-march=native", "-fopenmp", "-ffp-contract=off")
LDFLAGS = ("-fopenmp",)
HASHGRID_SOURCES = ("hashgrid.cpp",)
HASHGRID_NAMESPACE = "hypnerf_hashgrid"

STALE_AFTER_DAYS = 30

_build_lock = threading.Lock()


def cache_root() -> Path:
    """Folder holding the compiled extensions; ``HYPNERF_CACHE`` overrides the default."""
    root = os.environ.get("HYPNERF_CACHE")
    return Path(root).expanduser() if root else Path.home() / ".cache" / "hypnerf" / "ext"


def _cpu_identity() -> str:
    """CPU model and feature flags: binaries built with -march=native are only valid there."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return f"{platform.machine()} {platform.processor()}"
    wanted = ("model name", "flags", "Features", "CPU part")
    return "\n".join(sorted({line for line in lines if line.split(":")[0].strip() in wanted}))


def machine_summary() -> dict:
    """What a timing depends on: the CPU model, its core count and whether the hash-grid kernel's
    AVX-512 path can run (otherwise the portable path does, about 1.5x slower)."""
    identity = _cpu_identity()
    model = next((line.split(":", 1)[1].strip() for line in identity.splitlines() if line.startswith("model name")), platform.processor())
    return {"cpu": model, "cores": os.cpu_count(), "avx512": " avx512f" in f" {identity} ".replace("\n", " ")}


@functools.lru_cache(maxsize=None)
def _compiler_identity() -> str:
    cxx = os.environ.get("CXX", "c++")
    try:
        return subprocess.run([cxx, "--version"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return cxx


def build_key() -> str:
    """Hex digest identifying the binaries built from ``model/csrc`` on this machine."""
    h = hashlib.sha256()
    for path in sorted(p for p in CSRC.iterdir() if p.is_file()):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    for part in (" ".join(CFLAGS), " ".join(LDFLAGS), _compiler_identity(), _cpu_identity(), torch.__version__,
                 sys.version):
        h.update(part.encode() + b"\0")
    return h.hexdigest()[:20]


def library_path(stem: str) -> Path:
    """Where the compiled library for extension ``stem`` lives (or will live) in the cache."""
    name = f"{stem}_{build_key()}"
    return cache_root() / name / f"{name}.so"


def _build_or_load(stem: str, sources: tuple[str, ...]) -> Path:
    """Load the shared library of ``stem``, compiling it first if the cache lacks it."""
    library = library_path(stem)
    if library.exists():
        torch.ops.load_library(str(library))
        _mark_used(library)
        return library
    from torch.utils import cpp_extension

    library.parent.mkdir(parents=True, exist_ok=True)
    log.warning("compiling the %s C++ extension into %s (first use with these sources; takes a minute)",
                stem, library.parent)
    build_dir = Path(tempfile.mkdtemp(prefix="build-", dir=library.parent))
    try:
        name = library.stem
        cpp_extension.load(
            name=name,
            sources=[str(CSRC / s) for s in sources],
            extra_cflags=list(CFLAGS),
            extra_ldflags=list(LDFLAGS),
            build_directory=str(build_dir),
            is_python_module=False,
            verbose=False,
        )
        staged = library.with_suffix(f".{os.getpid()}.tmp")
        shutil.copyfile(build_dir / f"{name}.so", staged)
        os.replace(staged, library)
    finally:
        shutil.rmtree(build_dir, ignore_errors=True)
    log.info("built %s", library)
    prune_stale_builds(stem, keep=library.parent)
    return library


def _mark_used(library: Path) -> None:
    try:
        os.utime(library)
    except OSError:  # a read-only cache still loads
        pass


def prune_stale_builds(stem: str, keep: Path, max_age_days: float = STALE_AFTER_DAYS) -> list[Path]:
    """Delete the cache folders of ``stem`` other than ``keep`` whose library was last used more
    than ``max_age_days`` ago (or that hold no library: a build that died); returns them."""
    cutoff = time.time() - max_age_days * 86400
    removed = []
    for folder in cache_root().glob(f"{stem}_*"):
        if not folder.is_dir() or folder.resolve() == keep.resolve():
            continue
        library = folder / f"{folder.name}.so"
        last_used = library.stat().st_mtime if library.exists() else folder.stat().st_mtime
        if last_used < cutoff:
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
            log.info("removed %s (unused for over %g days)", folder, max_age_days)
    return removed


@functools.lru_cache(maxsize=1)
def hashgrid_ops():
    """The ``torch.ops`` namespace of the fused hash-grid kernel, built on first use.

    Raises whatever the build raised (no compiler, missing headers...); callers decide whether
    to fall back.
    """
    with _build_lock:
        _build_or_load("hashgrid", HASHGRID_SOURCES)
    return getattr(torch.ops, HASHGRID_NAMESPACE)


def main() -> None:
    """Build every extension ahead of time (``python -m model.nerf.encodings.kernels``)."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    hashgrid_ops()
    log.info("C++ extensions ready in %s", cache_root())


if __name__ == "__main__":
    main()
