"""Coherence between the live channels of a stream (docs/environment.md)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Query

from imunoise.web import deps

router = APIRouter()


@router.get("/coherence",
            summary="magnitude-squared coherence of every pair of a stream's IMU channels on "
                    "log-frequency points, exact 95 % intervals and the zero-coherence "
                    "threshold")
async def coherence(svc: deps.ServiceDep,
                    stream: str | None = Query(None, description="default: the first")
                    ) -> dict[str, Any]:
    try:
        return svc.coherence.document(stream)
    except KeyError as exc:
        raise HTTPException(404, str(exc.args[0])) from None
