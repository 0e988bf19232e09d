"""The model of a channel: its diagnosis, its state, changes to it and refits on demand."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request

from imunoise.analysis.channel_state import VALID_TERMS
from imunoise.analysis.terms import parse_model
from imunoise.web import deps
from imunoise.web.schemas import (
    ChannelCoefficientsOut,
    DiagnosisOut,
    ModelChangeOut,
    ModelChangeRequest,
    ModelOut,
    RefitRequest,
)
from imunoise.web.views import live as views

router = APIRouter()


@router.get("/diagnosis", response_model=DiagnosisOut,
            summary="missing terms, most significant first, with the error each would leave")
async def diagnosis(a: deps.AnalyzerDep) -> dict[str, Any]:
    return views.diagnosis(a)


@router.get("/model", response_model=ModelOut, summary="current model and error history")
async def get_model(a: deps.AnalyzerDep) -> dict[str, Any]:
    return views.model(a, VALID_TERMS)


@router.post("/model", response_model=ModelChangeOut, dependencies=[Depends(deps.require_token)],
             summary="add or remove a term; the reply carries the error before and after")
def post_model(change: ModelChangeRequest, request: Request) -> dict[str, Any]:
    a = deps.analyzer_named(request, change.channel)
    try:
        if change.add is not None:
            if change.add in a.model:
                raise ValueError(f"term {change.add!r} is already in the model")
            return views.model_change(a.add_term(change.add), a)
        if change.remove is not None:
            return views.model_change(a.remove_term(change.remove), a)
        if change.model is not None:
            return views.model_change(
                a.set_model([e.text() for e in parse_model(change.model).entries]), a)
        return views.model_change(a.set_model(change.terms or []), a)
    except ValueError as exc:
        raise HTTPException(400, str(exc)) from None


@router.post("/refit", response_model=ChannelCoefficientsOut,
             dependencies=[Depends(deps.require_token)],
             summary="refit a channel now; 'profile' gives the intervals of imunoise fit")
def post_refit(req: RefitRequest, request: Request) -> dict[str, Any]:
    a = deps.analyzer_named(request, req.channel)
    a.refit(full=req.intervals == "profile")
    return views.coefficients(a)
