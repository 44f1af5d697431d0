"""Content-addressed cache of generated NeRFs: field parameters plus their occupancy grid.

A NeRF's id is the sha256 of the bundle digest and its codes (``codes_nerf_id``) or of its
parameters (``params_nerf_id``, for NeRFs that no longer come from codes alone, such as finetuned
inversions), so the same request always names the same NeRF and a new bundle never serves an old
one. Entries live in a byte-bounded LRU in memory, written through to a byte-bounded LRU on disk.

Disk entries are one safetensors file each (safetensors: no pickle, zero-copy loading), with the
entry's metadata as JSON in the file's header, written to a temporary name and renamed into place,
so a reader never sees half a file and another process (an inversion worker) can ``put`` into the
same directory for the API process to ``get``. Recency on disk is the file's modification time,
refreshed on every hit, so every process sharing the directory evicts the same way.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from model.nerf.fields import FieldParams
from model.nerf.occupancy import OccupancyGrid

log = logging.getLogger(__name__)

_SUFFIX = ".safetensors"
_PARAM = "param."
_GRID = "grid."


@dataclass
class NerfEntry:
    """One generated NeRF: ``params`` (batch 1, CPU float32), its occupancy ``grid`` and JSON ``meta``."""

    params: FieldParams
    grid: OccupancyGrid
    meta: dict = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        tensors = [*self.params.values(), self.grid.occupied, self.grid.box_min, self.grid.box_max]
        return sum(t.numel() * t.element_size() for t in tensors)


def _digest(*parts: bytes) -> str:
    h = hashlib.sha256()
    for part in parts:
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    return h.hexdigest()


def _code_bytes(code) -> bytes:
    array = np.asarray(code, dtype="<f4").reshape(-1)
    return (array + np.float32(0.0)).tobytes()  # -0.0 + 0.0 = +0.0: equal codes, equal bytes


def codes_nerf_id(bundle_digest: str, shape, color) -> str:
    """The id of the NeRF the bundle ``bundle_digest`` generates from ``shape [S]`` and ``color [C]``
    (sha256 hex of the digest and the codes as little-endian float32)."""
    return _digest(b"codes", bundle_digest.encode(), _code_bytes(shape), _code_bytes(color))


def params_nerf_id(bundle_digest: str, params: FieldParams) -> str:
    """The id of a NeRF given by its parameters (sha256 hex over names, shapes and float32 values)."""
    parts = [b"params", bundle_digest.encode()]
    for name in sorted(params):
        value = params[name].detach().float().cpu().contiguous()
        parts += [name.encode(), repr(tuple(value.shape)).encode(), value.numpy().astype("<f4").tobytes()]
    return _digest(*parts)


def _is_nerf_id(nerf_id: str) -> bool:
    return len(nerf_id) == 64 and all(c in "0123456789abcdef" for c in nerf_id)


class NerfCache:
    """Byte-bounded LRU of :class:`NerfEntry` in memory, written through to a byte-bounded LRU on disk.

    ``memory_bytes`` or ``disk_bytes`` of 0 turns that tier off; an entry larger than a tier's
    budget is not kept in it. Thread-safe; several processes may share ``directory``.
    """

    def __init__(self, directory: Path, memory_bytes: int, disk_bytes: int):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.memory_bytes = int(memory_bytes)
        self.disk_bytes = int(disk_bytes)
        self._memory: OrderedDict[str, tuple[NerfEntry, int]] = OrderedDict()  # id -> (entry, bytes)
        self._memory_used = 0
        self._lock = threading.Lock()
        self._disk_lock = threading.Lock()
        self._counts = {"memory_hits": 0, "disk_hits": 0, "misses": 0, "memory_evictions": 0, "disk_evictions": 0}

    # memory tier -------------------------------------------------------------------------
    def _remember(self, nerf_id: str, entry: NerfEntry) -> None:
        size = entry.nbytes
        with self._lock:
            old = self._memory.pop(nerf_id, None)
            if old is not None:
                self._memory_used -= old[1]
            if size > self.memory_bytes:
                return
            self._memory[nerf_id] = (entry, size)
            self._memory_used += size
            while self._memory_used > self.memory_bytes:
                _, (_, evicted) = self._memory.popitem(last=False)
                self._memory_used -= evicted
                self._counts["memory_evictions"] += 1

    # disk tier ---------------------------------------------------------------------------
    def _path(self, nerf_id: str) -> Path:
        return self.directory / f"{nerf_id}{_SUFFIX}"

    def _write(self, nerf_id: str, entry: NerfEntry) -> None:
        tensors = {_PARAM + k: v.detach().float().cpu().contiguous() for k, v in entry.params.items()}
        tensors.update({_GRID + k: v.cpu().contiguous() for k, v in entry.grid.state_dict().items()})
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=".tmp-", suffix=_SUFFIX)
        os.close(fd)
        try:
            save_file(tensors, tmp, metadata={"meta": json.dumps(entry.meta)})
            os.replace(tmp, self._path(nerf_id))
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    def _read(self, nerf_id: str) -> NerfEntry | None:
        path = self._path(nerf_id)
        try:
            tensors = load_file(str(path))
            with open(path, "rb") as handle:
                header_len = int.from_bytes(handle.read(8), "little")
                header = json.loads(handle.read(header_len))
            os.utime(path)
        except FileNotFoundError:
            return None
        except (SafetensorError, OSError, ValueError) as exc:
            log.warning("dropping unreadable cache file %s: %s", path, exc)
            path.unlink(missing_ok=True)
            return None
        params = {k[len(_PARAM):]: v for k, v in tensors.items() if k.startswith(_PARAM)}
        grid = OccupancyGrid.from_state_dict({k[len(_GRID):]: v for k, v in tensors.items() if k.startswith(_GRID)})
        return NerfEntry(params, grid, json.loads(header.get("__metadata__", {}).get("meta", "{}")))

    def _disk_files(self) -> list[tuple[float, int, Path]]:
        files = []
        for path in self.directory.glob(f"*{_SUFFIX}"):
            if path.name.startswith(".tmp-"):
                continue
            try:
                stat = path.stat()
            except FileNotFoundError:  # evicted by another process meanwhile
                continue
            files.append((stat.st_mtime, stat.st_size, path))
        return files

    def _trim_disk(self) -> None:
        with self._disk_lock:
            files = sorted(self._disk_files())
            used = sum(size for _, size, _ in files)
            for _, size, path in files:
                if used <= self.disk_bytes:
                    break
                path.unlink(missing_ok=True)
                used -= size
                with self._lock:
                    self._counts["disk_evictions"] += 1

    # public ------------------------------------------------------------------------------
    def get(self, nerf_id: str) -> NerfEntry | None:
        """The entry, from memory or else from disk (then kept in memory), or ``None``."""
        with self._lock:
            held = self._memory.get(nerf_id)
            if held is not None:
                self._memory.move_to_end(nerf_id)
                self._counts["memory_hits"] += 1
                return held[0]
        entry = self._read(nerf_id) if self.disk_bytes > 0 and _is_nerf_id(nerf_id) else None
        with self._lock:
            self._counts["disk_hits" if entry is not None else "misses"] += 1
        if entry is not None:
            self._remember(nerf_id, entry)
        return entry

    def put(self, nerf_id: str, entry: NerfEntry) -> None:
        """Keep ``entry`` under ``nerf_id`` (a 64-hex-digit id) in memory and on disk."""
        if not _is_nerf_id(nerf_id):
            raise ValueError(f"a NeRF id is 64 lowercase hex digits (sha256), got {nerf_id!r}")
        params = {k: v.detach().float().cpu() for k, v in entry.params.items()}
        entry = NerfEntry(params, entry.grid.to("cpu"), dict(entry.meta))
        self._remember(nerf_id, entry)
        if 0 < entry.nbytes <= self.disk_bytes:
            self._write(nerf_id, entry)
            self._trim_disk()

    def stats(self) -> dict[str, int]:
        """Hit/miss/eviction counts of this process, and the bytes and entries of each tier."""
        files = self._disk_files()
        with self._lock:
            return {
                **self._counts,
                "memory_bytes": self._memory_used,
                "memory_entries": len(self._memory),
                "memory_budget_bytes": self.memory_bytes,
                "disk_bytes": sum(size for _, size, _ in files),
                "disk_entries": len(files),
                "disk_budget_bytes": self.disk_bytes,
            }
