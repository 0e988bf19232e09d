"""The current results: coefficients with intervals, Allan deviation and PSD."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from imunoise.web import deps
from imunoise.web.schemas import AllanOut, CoefficientsOut, PsdOut
from imunoise.web.views import live as views

router = APIRouter()


@router.get("/coefficients", response_model=CoefficientsOut,
            summary="current noise coefficients per channel, with units and 95 % intervals")
async def coefficients(svc: deps.ServiceDep) -> dict[str, Any]:
    out = {name: views.coefficients(svc.analyzers.get(name)) for name in svc.analyzers.channels}
    return {"channels": out,
            "samples_seen": sum(c["n_samples"] for c in out.values()),
            "record_length_s": max((c["duration_s"] for c in out.values()), default=0.0)}


@router.get("/allan", response_model=AllanOut,
            summary="Allan deviation with its 95 % band, the model and each term")
async def allan(a: deps.AnalyzerDep) -> dict[str, Any]:
    return views.allan(a)


@router.get("/psd", response_model=PsdOut, summary="PSD with its 95 % band and the model")
async def psd(a: deps.AnalyzerDep) -> dict[str, Any]:
    return views.psd(a)
