"""The HTTP API and dashboard of ``imunoise serve`` (FastAPI; OpenAPI at ``/docs``).

The app is thin: it reads what the live service publishes and forwards model changes to the
channel's analyzer. It never takes a file path from a request.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import threading
from collections.abc import AsyncIterator

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from starlette.middleware.trustedhost import TrustedHostMiddleware

from imunoise.live.service import LiveService
from imunoise.web.deps import TOKEN_HEADER
from imunoise.web.routes import coherence, curves, fleet, model, pages, status
from imunoise.web.routes.pages import STATIC_DIR

__all__ = ["LOOPBACK_HOSTS", "STATIC_DIR", "TOKEN_HEADER", "create_app"]

LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")


def _version() -> str:
    """The installed imunoise's version (from its distribution metadata: ``web`` does not
    import the command-line package)."""
    try:
        return importlib.metadata.version("imunoise")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def create_app(service: LiveService, token: str | None = None,
               event_interval_s: float = 0.5,
               allowed_hosts: tuple[str, ...] | None = LOOPBACK_HOSTS,
               catalog: str | None = None) -> FastAPI:
    """Build the app around a running :class:`LiveService`: the routers of ``imunoise.web.routes``,
    what they depend on in ``app.state`` (``imunoise.web.deps``), the static files.

    Args:
        service: the live service whose state is served.
        token: when set, mutating endpoints require it (``Authorization: Bearer TOKEN`` or the
            ``X-Imunoise-Token`` header).
        event_interval_s: how often the event stream checks for new results, s.
        allowed_hosts: accepted ``Host`` headers (None: any). The loopback default stops a
            web page from reaching the service through DNS rebinding.
        catalog: fleet catalogue folder shown at ``/fleet`` (None: ``/fleet`` is 404).
    """
    closing = asyncio.Event()

    @contextlib.asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        yield
        closing.set()  # ends the event streams so the server can stop

    app = FastAPI(title="imunoise", lifespan=lifespan, version=_version(),
                  description="Live Allan variance, PSD, noise-model fit and diagnosis of an "
                              "inertial sensor. Values in SI units unless labelled.")
    app.state.service = service
    app.state.token = token
    app.state.catalog = catalog
    app.state.event_interval_s = event_interval_s
    app.state.closing = closing
    # Set by the server when a stop is requested: the event streams end at once instead of
    # holding the graceful shutdown open (the lifespan's ``closing`` comes only after it).
    app.state.stop_streams = threading.Event()
    for module in (pages, status, curves, coherence, model, fleet):
        app.include_router(module.router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    if allowed_hosts is not None:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=list(allowed_hosts))
    return app
