"""The project's on-disk cache: ``$HYPNERF_CACHE``, else ``~/.cache/hypnerf``, one subfolder per kind."""

from __future__ import annotations

import os
from pathlib import Path


def cache_folder(kind: str) -> Path:
    """The cache's subfolder for ``kind`` (not created)."""
    root = os.environ.get("HYPNERF_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "hypnerf") / kind
