"""Content-addressed storage of a job's uploaded files, so a re-queued job still has its inputs.

A blob's name is the sha256 of its bytes, so the same upload is stored once and a request's hash
can name its files. On one machine blobs are files under the state directory (written to a
temporary name and renamed, so a reader never sees half a file); with Redis they live in Redis
next to the job records, so a worker on another machine reads what an API replica received.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import redis

REDIS_BLOB_TTL_S = 14 * 24 * 3600  # inputs outlive any job that can still be re-queued


def blob_name(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class MissingBlob(LookupError):
    """An input file named by a job is not in the store."""


class DiskBlobs:
    """Blobs as files ``<root>/<aa>/<sha256>``."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def _path(self, name: str) -> Path:
        return self.root / name[:2] / name

    def put(self, data: bytes) -> str:
        name = blob_name(data)
        path = self._path(name)
        if not path.exists():
            path.parent.mkdir(exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
            with os.fdopen(fd, "wb") as handle:
                handle.write(data)
            os.replace(tmp, path)
        return name

    def get(self, name: str) -> bytes:
        try:
            return self._path(name).read_bytes()
        except FileNotFoundError:
            raise MissingBlob(f"input {name} is missing from {self.root}") from None


class RedisBlobs:
    """Blobs as Redis strings ``<prefix>:blob:<sha256>`` that expire after two weeks."""

    def __init__(self, url: str, prefix: str = "hypnerf"):
        self.redis = redis.Redis.from_url(url)
        self.prefix = prefix

    def put(self, data: bytes) -> str:
        name = blob_name(data)
        self.redis.set(f"{self.prefix}:blob:{name}", data, ex=REDIS_BLOB_TTL_S)
        return name

    def get(self, name: str) -> bytes:
        data = self.redis.get(f"{self.prefix}:blob:{name}")
        if data is None:
            raise MissingBlob(f"input {name} is missing from Redis (inputs expire after {REDIS_BLOB_TTL_S // 86400} days)")
        return data
