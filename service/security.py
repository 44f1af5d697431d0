"""Bearer API keys (``HYPNERF_API_KEYS``), compared in constant time (``hmac.compare_digest``).

With no keys configured (only allowed on loopback, see ``service.settings``) every request passes.
Health endpoints never require a key, so probes work without secrets.
"""

from __future__ import annotations

import hmac

from fastapi import Request

from service.problems import ProblemError


def require_api_key(request: Request) -> None:
    """Dependency of every protected router: 401 unless ``Authorization: Bearer <key>`` names a configured key."""
    keys: list[bytes] = request.app.state.api_keys
    if not keys:
        return
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    given = token.strip().encode()
    # compare against every key so the time taken does not reveal which (or whether one) matched
    matched = False
    for key in keys:
        matched |= hmac.compare_digest(given, key)
    if scheme.lower() != "bearer" or not matched:
        raise ProblemError(401, "Unauthorized", "send a valid API key as 'Authorization: Bearer <key>'", kind="unauthorized",
                           headers={"WWW-Authenticate": 'Bearer realm="hypnerf"'})
