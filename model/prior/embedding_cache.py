"""Embeddings of a dataset object's views, computed once and kept on disk.

Embedding thousands of renders with the image network takes minutes on a CPU, and training the
query network, its evaluation and the retrieval bank all need the same ones. Each object's
embeddings are one safetensors file under ``$HYPNERF_CACHE/embeddings`` (default
``~/.cache/hypnerf/embeddings``), named by a digest of everything that changes them: the
embedder's name and version (weights and preprocessing), the object folder, its
``transforms.json`` (size and modification time, which change when the object is re-rendered),
the frame split and the view numbers. A changed input gets a new file; an unchanged one is
read back. Files are written to a temporary name and renamed, so an interrupted run leaves none
half-written.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from model.data.dataset import TRANSFORMS_FILE, load_views
from model.nerf.cache import cache_folder
from model.prior.embedders import embed_images

log = logging.getLogger(__name__)


def cache_root() -> Path:
    return cache_folder("embeddings")


def cache_key(embedder, folder: Path, split: str, views: list[int]) -> str:
    folder = Path(folder).resolve()
    stat = (folder / TRANSFORMS_FILE).stat()
    text = f"{embedder.name}:{embedder.version()}:{folder}:{stat.st_size}:{stat.st_mtime_ns}:{split}:{','.join(map(str, views))}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def spread_views(count: int, available: int) -> list[int]:
    """``count`` view numbers spread evenly over ``available`` views (all of them when fewer)."""
    if count < 1:
        raise ValueError(f"embed at least one view per object, got {count}")
    if count >= available:
        return list(range(available))
    return sorted({int(round(i * (available - 1) / (count - 1))) for i in range(count)}) if count > 1 else [available // 2]


def split_frames(folder: Path, split: str) -> int:
    """How many frames of ``split`` the object's ``transforms.json`` lists (without reading images)."""
    frames = json.loads((Path(folder) / TRANSFORMS_FILE).read_text()).get("frames", [])
    return sum(1 for f in frames if isinstance(f, dict) and f.get("split", "train") == split)


def view_embeddings(embedder, folder: Path, split: str, count: int, cache: Path | None = None) -> torch.Tensor:
    """Embeddings ``[V, E]`` of ``count`` views (spread over the frame split) of the object in ``folder``."""
    folder = Path(folder)
    picks = spread_views(count, split_frames(folder, split))
    cache = cache_root() if cache is None else Path(cache)
    path = cache / f"{cache_key(embedder, folder, split, picks)}.safetensors"
    if path.is_file():
        return load_file(str(path))["embeddings"]
    views = load_views(folder, split=split)
    embeddings = embed_images(embedder, views.images[picks]).float().contiguous()
    cache.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".tmp")
    save_file({"embeddings": embeddings}, str(partial))
    partial.replace(path)
    log.debug("embedded %d views of %s into %s", len(picks), folder.name, path)
    return embeddings
