"""What the routes depend on: the live service, a channel's analyzer, the change token.

Set up by :func:`imunoise.web.app.create_app` in ``app.state``; the routers take them through
FastAPI's
``Depends`` so that none of them holds state of its own.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Query, Request

from imunoise.live.channel import LiveChannel
from imunoise.live.service import LiveService

TOKEN_HEADER = "X-Imunoise-Token"


def service(request: Request) -> LiveService:
    """The live service the app serves."""
    return request.app.state.service


def _analyzer(request: Request, channel: str | None) -> LiveChannel:
    analyzers = service(request).analyzers
    channels = analyzers.channels
    if channel is None:
        if not channels:
            raise HTTPException(503, "no data analysed yet; retry in a few seconds")
        channel = channels[0]
    if channel not in channels:
        valid = ", ".join(channels) or "(none yet)"
        raise HTTPException(404, f"unknown channel {channel!r}; valid channels: {valid}")
    return analyzers.get(channel)


def analyzer(request: Request,
             channel: str | None = Query(None, description="e.g. gyro_x; default: the first"),
             ) -> LiveChannel:
    """The analyzer of the ``channel`` query parameter (404 listing the valid channels)."""
    return _analyzer(request, channel)


def analyzer_named(request: Request, channel: str | None) -> LiveChannel:
    """The analyzer of a channel named in a request body."""
    return _analyzer(request, channel)


def require_token(request: Request) -> None:
    """401 unless the request carries the app's token (when it has one)."""
    token = request.app.state.token
    if token is None:
        return
    given = request.headers.get(TOKEN_HEADER, "")
    auth = request.headers.get("Authorization", "")
    if auth.lower().startswith("bearer "):
        given = given or auth[7:].strip()
    if not given or not hmac.compare_digest(given.encode(), token.encode()):
        raise HTTPException(401, "this server requires a token for changes: send "
                                 f"'Authorization: Bearer TOKEN' or '{TOKEN_HEADER}'")


ServiceDep = Annotated[LiveService, Depends(service)]
"""A route parameter that receives the live service."""
AnalyzerDep = Annotated[LiveChannel, Depends(analyzer)]
"""A route parameter that receives the analyzer of the ``channel`` query parameter."""
