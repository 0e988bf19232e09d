"""Liveness, the channels, and the server-sent event stream the dashboard follows."""

from __future__ import annotations

import asyncio
import json
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import StreamingResponse

from imunoise.analysis.channel_state import VALID_TERMS
from imunoise.web import deps
from imunoise.web.schemas import HealthOut

router = APIRouter()


@router.get("/health", response_model=HealthOut, summary="liveness, device state, drops, file")
async def health(svc: deps.ServiceDep) -> dict[str, Any]:
    return svc.health()


@router.get("/channels", summary="channels being analysed")
async def channels(svc: deps.ServiceDep) -> dict[str, Any]:
    return {"channels": svc.analyzers.channels, "valid_terms": list(VALID_TERMS)}


@router.get("/events", summary="server-sent events: 'update' whenever results change")
async def events(request: Request, svc: deps.ServiceDep
                 ) -> StreamingResponse:
    state = request.app.state
    interval = state.event_interval_s

    async def stream():
        last = None
        yield "retry: 2000\n\n"
        idle = 0.0
        while not (state.closing.is_set() or state.stop_streams.is_set()):
            if await request.is_disconnected():
                break
            rev = svc.revision
            if rev != last:
                last = rev
                idle = 0.0
                h = svc.health()
                payload = {"revision": rev, "channels": h["channels"], "samples": h["samples"],
                           "state": h["device"]["state"], "file": h["recording"]["file"],
                           "status": h["status"]}
                yield f"event: update\ndata: {json.dumps(payload)}\n\n"
            elif idle >= 15.0:
                idle = 0.0
                yield ": keep-alive\n\n"
            try:
                await asyncio.wait_for(state.closing.wait(), interval)
            except TimeoutError:
                idle += interval

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache"})
