"""Webhooks on job completion (httpx): an allow-list of targets, an HMAC-SHA256 signature, retries.

A target is refused at submission unless its host (or ``host:port``) is in
``HYPNERF_WEBHOOK_ALLOW`` (empty by default: no webhooks) and a signing secret is configured, so
the service can never be made to POST to arbitrary hosts (server-side request forgery). Hosts are
compared literally, not resolved, so a name cannot be re-pointed at a forbidden address later.
The body is the job as ``GET /v1/jobs/{id}`` shows it; ``X-Hypnerf-Signature: sha256=<hex>`` is
the HMAC-SHA256 of exactly those bytes under the secret, which a receiver recomputes and compares
in constant time. Delivery is retried with exponential backoff on connection errors, timeouts and
5xx/408/429 answers; the outcome is recorded on the job.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import time
import uuid
from urllib.parse import urlsplit

import httpx

from service.schemas.jobs import iso_time
from service.settings import Settings

log = logging.getLogger(__name__)

SIGNATURE_HEADER = "X-Hypnerf-Signature"
ATTEMPTS = 4
FIRST_BACKOFF_S = 0.5
TIMEOUT_S = 10.0
_RETRY_STATUSES = {408, 429}


def refusal(url: str, settings: Settings) -> str | None:
    """Why ``url`` may not receive webhooks, or ``None`` when it may."""
    allowed = ", ".join(settings.webhook_allow) or "none"
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        return f"is not a valid URL ({exc})"
    if parts.scheme not in ("http", "https") or not parts.hostname:
        return "must be an http or https URL with a host"
    if parts.username or parts.password:
        return "must not carry credentials; authenticate the webhook by its signature header instead"
    host = parts.hostname.lower()
    shown = f"[{host}]" if ":" in host else host
    port = port or (443 if parts.scheme == "https" else 80)
    if shown not in settings.webhook_allow and f"{shown}:{port}" not in settings.webhook_allow:
        return f"host {shown}:{port} is not in the webhook allow-list (HYPNERF_WEBHOOK_ALLOW; allowed: {allowed})"
    if settings.webhook_secret is None or not settings.webhook_secret.get_secret_value():
        return "webhooks need a signing secret; set HYPNERF_WEBHOOK_SECRET on the server"
    return None


def signature(body: bytes, secret: str) -> str:
    """The signature header's value: ``sha256=`` and the hex HMAC-SHA256 of ``body``."""
    return "sha256=" + hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()


def deliver(url: str, body: bytes, secret: str, event: str, *, sleep=time.sleep) -> dict:
    """POST ``body`` to ``url`` until it is accepted (2xx) or the attempts run out; returns the
    outcome ``{"delivered", "attempts", "status_code", "error", "delivered_at"}``."""
    headers = {"Content-Type": "application/json", SIGNATURE_HEADER: signature(body, secret), "X-Hypnerf-Event": event,
               "X-Hypnerf-Delivery": uuid.uuid4().hex, "User-Agent": "hypnerf-webhook"}
    outcome = {"delivered": False, "attempts": 0, "status_code": None, "error": None, "delivered_at": None}
    with httpx.Client(timeout=TIMEOUT_S, follow_redirects=False) as client:
        for attempt in range(ATTEMPTS):
            outcome["attempts"] = attempt + 1
            try:
                response = client.post(url, content=body, headers=headers)
            except httpx.HTTPError as exc:
                outcome.update(status_code=None, error=f"{type(exc).__name__}: {exc}")
            else:
                outcome["status_code"] = response.status_code
                if response.is_success:
                    outcome.update(delivered=True, error=None, delivered_at=iso_time(time.time()))
                    return outcome
                outcome["error"] = f"answered HTTP {response.status_code}"
                if response.status_code < 500 and response.status_code not in _RETRY_STATUSES:
                    return outcome  # the receiver refuses this delivery; repeating it will not help
            if attempt + 1 < ATTEMPTS:
                sleep(FIRST_BACKOFF_S * 2**attempt)
    log.warning("webhook to %s failed after %d attempts: %s", url, outcome["attempts"], outcome["error"])
    return outcome
