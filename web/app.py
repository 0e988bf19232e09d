"""The HTTP API and dashboard of ``imunoise serve`` (FastAPI; OpenAPI at ``/docs``).

The app is thin: it reads what the live service publishes and forwards model changes to the
channel's analyzer. It never takes a file path from a request.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import importlib.metadata
import json
import threading
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from fastapi import Depends, FastAPI, HTTPException, Query, Request
from fastapi.responses import FileResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.middleware.trustedhost import TrustedHostMiddleware

from analysis.rolling import VALID_TERMS, ChannelAnalyzer
from analysis.terms import parse_model
from live.service import LiveService
from web.models import (
    AllanCurve,
    ChannelCoefficients,
    Coefficients,
    Diagnosis,
    Health,
    ModelChange,
    ModelChangeRequest,
    ModelState,
    PsdCurve,
    RefitRequest,
)

STATIC_DIR = Path(__file__).resolve().parent / "static"
TOKEN_HEADER = "X-Imunoise-Token"


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
               allowed_hosts: tuple[str, ...] | None = LOOPBACK_HOSTS) -> FastAPI:
    """Build the app around a running :class:`LiveService`.

    Args:
        service: the live service whose state is served.
        token: when set, mutating endpoints require it (``Authorization: Bearer TOKEN`` or the
            ``X-Imunoise-Token`` header).
        event_interval_s: how often the event stream checks for new results, s.
        allowed_hosts: accepted ``Host`` headers (None: any). The loopback default stops a
            web page from reaching the service through DNS rebinding.
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
    app.state.closing = closing
    # Set by the server when a stop is requested: the event streams end at once instead of
    # holding the graceful shutdown open (the lifespan's ``closing`` comes only after it).
    app.state.stop_streams = threading.Event()

    def require_token(request: Request) -> None:
        if token is None:
            return
        given = request.headers.get(TOKEN_HEADER, "")
        auth = request.headers.get("Authorization", "")
        if auth.lower().startswith("bearer "):
            given = given or auth[7:].strip()
        if not given or not hmac.compare_digest(given.encode(), token.encode()):
            raise HTTPException(401, "this server requires a token for changes: send "
                                     f"'Authorization: Bearer TOKEN' or '{TOKEN_HEADER}'")

    def analyzer(channel: str | None) -> ChannelAnalyzer:
        channels = service.analyzers.channels
        if channel is None:
            if not channels:
                raise HTTPException(503, "no data analysed yet; retry in a few seconds")
            channel = channels[0]
        try:
            return service.analyzers.get(channel)
        except KeyError as exc:
            raise HTTPException(404, str(exc.args[0])) from None

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    @app.get("/favicon.ico", include_in_schema=False)
    def favicon() -> Response:
        return Response(status_code=204)

    @app.get("/health", response_model=Health, summary="liveness, device state, drops, file")
    async def health() -> dict[str, Any]:
        return service.health()

    @app.get("/channels", summary="channels being analysed")
    async def channels() -> dict[str, Any]:
        return {"channels": service.analyzers.channels, "valid_terms": list(VALID_TERMS)}

    @app.get("/coefficients", response_model=Coefficients,
             summary="current noise coefficients per channel, with units and 95 % intervals")
    async def coefficients() -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name in service.analyzers.channels:
            out[name] = service.analyzers.get(name).coefficients()
        return {"channels": out,
                "samples_seen": sum(c["n_samples"] for c in out.values()),
                "record_length_s": max((c["duration_s"] for c in out.values()), default=0.0)}

    @app.get("/allan", response_model=AllanCurve,
             summary="Allan deviation with its 95 % band, the model and each term")
    async def allan(channel: str | None = Query(None, description="e.g. gyro_x")) -> dict[str, Any]:
        return analyzer(channel).allan()

    @app.get("/psd", response_model=PsdCurve, summary="PSD with its 95 % band and the model")
    async def psd(channel: str | None = Query(None, description="e.g. gyro_x")) -> dict[str, Any]:
        return analyzer(channel).psd()

    @app.get("/diagnosis", response_model=Diagnosis,
             summary="missing terms, most significant first, with the error each would leave")
    async def diagnosis(channel: str | None = Query(None)) -> dict[str, Any]:
        return analyzer(channel).diagnosis()

    @app.get("/model", response_model=ModelState, summary="current model and error history")
    async def get_model(channel: str | None = Query(None)) -> dict[str, Any]:
        a = analyzer(channel)
        d = a.diagnosis()
        return {"channel": a.channel, "model": d["model"], "model_revision": d["model_revision"],
                "valid_terms": list(VALID_TERMS), "error": d["error"], "history": a.history()}

    @app.post("/model", response_model=ModelChange, dependencies=[Depends(require_token)],
              summary="add or remove a term; the reply carries the error before and after")
    def post_model(change: ModelChangeRequest) -> dict[str, Any]:
        a = analyzer(change.channel)
        try:
            if change.add is not None:
                if change.add in a.model:
                    raise ValueError(f"term {change.add!r} is already in the model")
                result = a.add_term(change.add)
            elif change.remove is not None:
                result = a.remove_term(change.remove)
            elif change.model is not None:
                result = a.set_model([e.text() for e in parse_model(change.model).entries])
            else:
                result = a.set_model(change.terms or [])
        except ValueError as exc:
            raise HTTPException(400, str(exc)) from None
        return result

    @app.post("/refit", response_model=ChannelCoefficients,
              dependencies=[Depends(require_token)],
              summary="refit a channel now; 'profile' gives the intervals of imunoise fit")
    def post_refit(req: RefitRequest) -> dict[str, Any]:
        a = analyzer(req.channel)
        a.refit(full=req.intervals == "profile")
        return a.coefficients()

    @app.get("/events", summary="server-sent events: 'update' whenever results change")
    async def events(request: Request) -> StreamingResponse:
        async def stream():
            last = None
            yield "retry: 2000\n\n"
            idle = 0.0
            while not (app.state.closing.is_set() or app.state.stop_streams.is_set()):
                if await request.is_disconnected():
                    break
                rev = service.revision
                if rev != last:
                    last = rev
                    idle = 0.0
                    h = service.health()
                    payload = {"revision": rev, "channels": h["channels"],
                               "samples": h["samples"], "state": h["device"]["state"],
                               "file": h["recording"]["file"], "status": h["status"]}
                    yield f"event: update\ndata: {json.dumps(payload)}\n\n"
                elif idle >= 15.0:
                    idle = 0.0
                    yield ": keep-alive\n\n"
                try:
                    await asyncio.wait_for(app.state.closing.wait(), event_interval_s)
                except TimeoutError:
                    idle += event_interval_s
        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache"})

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    if allowed_hosts is not None:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=list(allowed_hosts))
    return app
