"""The real server in a subprocess: ``hypnerf serve`` (uvicorn) on a free loopback port, driven
over HTTP, for the integration tests and the service benchmark.

::

    from service.process import ServiceServer

    with ServiceServer(bundle, state_dir, env={"HYPNERF_CACHE_MEMORY_BYTES": "0"}) as server:
        httpx.get(server.url + "/readyz")
        server.restart()           # same port, state and settings (e.g. after a SIGKILL: server.kill())

``env`` adds ``HYPNERF_*`` settings; by default no embedded job workers are started
(``HYPNERF_WORKERS=0``) and torch uses one thread (``threads``; None leaves the environment's
setting). ``start()`` waits until ``/readyz`` answers 200 and fails with the server's log if it
exits or times out.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Self

import httpx

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class ServiceServer:
    def __init__(self, bundle: Path, state_dir: Path, env: dict[str, str] | None = None, timeout: float = 90.0, threads: int | None = 1):
        self.bundle = Path(bundle)
        self.state_dir = Path(state_dir)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.timeout = timeout
        self.env = {**os.environ, **({"OMP_NUM_THREADS": str(threads)} if threads is not None else {}), "HYPNERF_WORKERS": "0",
                    "HYPNERF_STATE_DIR": str(self.state_dir), **(env or {})}
        self.log_path = self.state_dir / "server.log"
        self.process: subprocess.Popen | None = None

    def start(self) -> Self:
        self.state_dir.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "model.cli", "serve", "--bundle", str(self.bundle), "--port", str(self.port), "--log-level", "warning"],
                cwd=ROOT, env=self.env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"the server exited with {self.process.returncode}:\n{self.log()}")
            try:
                if httpx.get(self.url + "/readyz", timeout=2.0).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"the server was not ready within {self.timeout:.0f} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-5000:] if self.log_path.exists() else ""

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process = None

    def kill(self) -> None:
        """SIGKILL: the server gets no chance to clean up."""
        if self.process is not None:
            self.process.kill()
            self.process.wait()
        self.process = None

    def restart(self) -> Self:
        self.stop()
        return self.start()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
