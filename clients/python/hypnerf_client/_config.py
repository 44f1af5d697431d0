"""A client's settings (server URL, API key, timeout, retry policy, headers) and what both clients
do with them: build each request and decide whether a failure is retried.

``HYPNERF_URL`` and ``HYPNERF_API_KEY`` are read when the client is not given a URL or key, so
code and examples run unchanged against any server.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import platform
from collections.abc import Mapping
from dataclasses import dataclass

import httpx

from hypnerf_client._calls import Call
from hypnerf_client._retry import RetryPolicy
from hypnerf_client._version import __version__

log = logging.getLogger("hypnerf_client")

DEFAULT_URL = "http://127.0.0.1:8000"
DEFAULT_TIMEOUT = 60.0
USER_AGENT = f"hypnerf-client/{__version__} httpx/{httpx.__version__} python/{platform.python_version()}"

Timeout = float | httpx.Timeout | None

UNSET = object()
"""``with_options(timeout=...)`` not given (``None`` is a valid timeout: wait forever)."""


@dataclass(frozen=True)
class Config:
    base_url: str
    api_key: str | None
    timeout: Timeout
    retry: RetryPolicy
    headers: Mapping[str, str]

    @classmethod
    def create(cls, base_url: str | None, api_key: str | None, timeout: Timeout, max_retries: int, backoff: float,
               headers: Mapping[str, str] | None) -> Config:
        url = (base_url or os.environ.get("HYPNERF_URL") or DEFAULT_URL).rstrip("/")
        if not url.startswith(("http://", "https://")):
            raise ValueError(f"base_url must start with http:// or https://, got {url!r}")
        key = api_key if api_key is not None else os.environ.get("HYPNERF_API_KEY") or None
        return cls(url, key, timeout, RetryPolicy(max_retries=max_retries, backoff=backoff), dict(headers or {}))

    def replace(self, timeout: Timeout | object, max_retries: int | None) -> Config:
        changes: dict = {}
        if timeout is not UNSET:
            changes["timeout"] = timeout
        if max_retries is not None:
            changes["retry"] = dataclasses.replace(self.retry, max_retries=max_retries)
        return dataclasses.replace(self, **changes)

    def build(self, http: httpx.Client | httpx.AsyncClient, call: Call) -> httpx.Request:
        headers = {"User-Agent": USER_AGENT, "Accept": "application/json", **self.headers, **call.headers}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        return http.build_request(call.method, self.base_url + call.path, params=call.params, json=call.json, data=call.data,
                                  files=call.files, headers=headers, timeout=self.timeout)

    def retry_delay(self, call: Call, retries_done: int, *, response: httpx.Response | None = None,
                    error: httpx.TransportError | None = None) -> float | None:
        """Seconds to wait before repeating ``call``, or None when the failure is final."""
        if response is not None:
            delay = self.retry.after_status(retries_done, response.status_code, response.headers, call.idempotent)
            reason = f"answered {response.status_code}"
        else:
            delay = self.retry.after_transport(retries_done, error, call.idempotent)
            reason = f"{type(error).__name__}"
        if delay is not None:
            log.info("%s %s %s; retry %d of %d in %.2f s", call.method, call.path, reason, retries_done + 1, self.retry.max_retries, delay)
        return delay
