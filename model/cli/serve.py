"""``hypnerf serve``: serve a bundle over HTTP with uvicorn (the FastAPI app of ``service.app``).

Options left out take the ``HYPNERF_*`` settings (``service.settings.Settings``), whose defaults
bind 127.0.0.1:8000 and serve ``bundles/chair-demo``.
"""

from __future__ import annotations

import argparse
import logging

log = logging.getLogger("hypnerf.serve")


def register(parser: argparse.ArgumentParser) -> None:
    from service.settings import Settings

    fields = Settings.model_fields
    parser.add_argument("--bundle", help=f"bundle folder written by `hypnerf export` (default HYPNERF_BUNDLE or {fields['bundle'].default})")
    parser.add_argument("--host", help=f"address to bind (default HYPNERF_HOST or {fields['host'].default}; any other than loopback "
                                       "needs HYPNERF_API_KEYS)")
    parser.add_argument("--port", type=int, help=f"port (default HYPNERF_PORT or {fields['port'].default})")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    parser.set_defaults(func=cmd_serve)


def cmd_serve(args) -> int:
    import uvicorn
    from pydantic import ValidationError

    from service.app import create_app
    from service.settings import Settings

    overrides = {name: getattr(args, name) for name in ("bundle", "host", "port") if getattr(args, name) is not None}
    try:
        settings = Settings(**overrides)
    except ValidationError as error:
        raise ValueError("; ".join(e["msg"].removeprefix("Value error, ") for e in error.errors())) from None
    if not (settings.bundle / "manifest.json").is_file():
        raise FileNotFoundError(f"{settings.bundle} is not a bundle (no manifest.json); write one with "
                                "`hypnerf export --run RUN --out BUNDLE` or pass --bundle")
    log.info("serving %s on http://%s:%d (state in %s)", settings.bundle, settings.host, settings.port, settings.state_dir)
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=args.log_level)
    return 0
