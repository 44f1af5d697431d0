"""What a cached result depends on: a digest of the source files that compute it.

A cached fit or evaluation is reused only when its config and the digest of the code that made it
both match, so a change to the renderer or the optimiser invalidates results made before it.
"""

from __future__ import annotations

import hashlib
from functools import cache
from pathlib import Path

MODEL_ROOT = Path(__file__).resolve().parent.parent
SOURCE_SUFFIXES = (".py", ".cpp", ".h")


@cache
def source_digest(*parts: str) -> str:
    """sha256 (16 hex digits) of the sources under ``model/<part>`` (a folder or a file), in path order."""
    digest = hashlib.sha256()
    for part in parts:
        root = MODEL_ROOT / part
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.suffix in SOURCE_SUFFIXES)
        if not files:
            raise ValueError(f"no sources under model/{part}")
        for path in files:
            digest.update(str(path.relative_to(MODEL_ROOT)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
