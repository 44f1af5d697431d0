"""The service's settings, read from ``HYPNERF_*`` environment variables (pydantic-settings).

Every setting has a safe default for one machine: bind 127.0.0.1, state under ``runs/service``,
bounded caches and request limits. Nested limits use ``__``, e.g.
``HYPNERF_LIMITS__MAX_RENDER_SIDE=1024``; lists are comma-separated
(``HYPNERF_API_KEYS=key-one,key-two``). Binding anywhere but loopback without API keys is refused,
so a server is never exposed by accident.
"""

from __future__ import annotations

import ipaddress
import os
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

MiB = 1 << 20


class Limits(BaseModel):
    """Caps on what one request may ask for; larger asks are answered 4xx, never attempted."""

    max_body_bytes: int = Field(64 * MiB, ge=1024, description="request bodies above this are refused with 413, before they are read")
    max_image_pixels: int = Field(16_000_000, ge=1, description="Pillow's decompression-bomb guard: uploaded images with more pixels are refused")
    max_render_side: int = Field(1024, ge=16, description="largest render width or height")
    max_turntable_side: int = Field(512, ge=16, description="largest turntable frame width or height")
    max_turntable_frames: int = Field(120, ge=1)
    max_mesh_resolution: int = Field(384, ge=16, description="largest marching-cubes grid per axis")
    max_texture_size: int = Field(2048, ge=64, description="largest baked UV texture side")
    max_pending_renders: int = Field(32, ge=1, description="renders and meshes queued or running at once; more are answered 429")
    max_retrieve_k: int = Field(50, ge=1)
    max_text_chars: int = Field(1000, ge=1)
    max_tto_steps: int = Field(2000, ge=1, description="largest number of test-time-optimisation steps an inversion job may ask for")
    max_queued_jobs: int = Field(64, ge=1, description="jobs queued or running at once; more are answered 429")
    max_upload_images: int = Field(64, ge=1, description="images in one inversion job")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Settings(BaseSettings):
    """Service settings; environment variables ``HYPNERF_<NAME>`` override the defaults."""

    model_config = SettingsConfigDict(env_prefix="HYPNERF_", env_nested_delimiter="__", extra="ignore")

    bundle: Path = Field(Path("bundles/chair-demo"), description="the bundle folder served (written by `hypnerf export`)")
    verify_bundle: bool = Field(True, description="check every file's sha256 against the manifest at start-up")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    api_keys: Annotated[list[SecretStr], NoDecode] = Field(default_factory=list, description="bearer API keys; required when not bound to loopback")
    state_dir: Path = Field(Path("runs/service"), description="job database and the NeRF disk cache")
    cache_memory_bytes: int = Field(512 * MiB, ge=0, description="bytes of generated NeRFs kept in memory (LRU)")
    cache_disk_bytes: int = Field(4096 * MiB, ge=0, description="bytes of generated NeRFs kept on disk under state_dir/nerfs (LRU)")
    grid_resolution: int | None = Field(None, ge=8, le=256, description="occupancy grid of each generated NeRF; default: the bundle's, else 64")
    render_workers: int = Field(2, ge=1, description="threads rendering and meshing (CPU work never runs on the event loop)")
    torch_threads: int | None = Field(None, ge=1, description="torch intra-op threads; default: CPU cores / render_workers")
    limits: Limits = Field(default_factory=Limits)
    # the job system
    workers: int = Field(1, ge=0, description="inversion worker processes started with the server (0: run workers separately)")
    broker: Literal["sqlite", "redis"] = "sqlite"
    redis_url: str = "redis://127.0.0.1:6379/0"
    webhook_allow: Annotated[list[str], NoDecode] = Field(default_factory=list, description="hosts webhooks may be sent to (host or host:port)")
    webhook_secret: SecretStr | None = Field(None, description="HMAC-SHA256 key signing webhook bodies")
    job_lease_s: float = Field(30.0, ge=1.0, description="seconds a worker's lease on a running job lasts without a heartbeat; the job of a dead worker is re-queued after it")
    job_max_attempts: int = Field(3, ge=1, description="starts of one inversion job before it fails (each worker lost while running it uses one)")
    cache_dir: Path | None = Field(None, description="NeRF disk cache folder (default state_dir/nerfs); shared disk when replicas and workers run on several machines")

    @field_validator("api_keys", "webhook_allow", mode="before")
    @classmethod
    def _comma_separated(cls, value):
        if isinstance(value, str):
            return [part.strip() for part in value.split(",") if part.strip()]
        return value

    @model_validator(mode="after")
    def _keys_when_exposed(self) -> Settings:
        if not _is_loopback(self.host) and not self.api_keys:
            raise ValueError(
                f"binding {self.host} exposes the service beyond this machine; set HYPNERF_API_KEYS "
                "(comma-separated bearer keys) or bind 127.0.0.1"
            )
        return self

    @property
    def nerf_cache_dir(self) -> Path:
        return self.cache_dir or self.state_dir / "nerfs"

    @property
    def intra_op_threads(self) -> int:
        return self.torch_threads or max(1, (os.cpu_count() or 1) // self.render_workers)

    def key_values(self) -> list[bytes]:
        return [key.get_secret_value().encode() for key in self.api_keys]
