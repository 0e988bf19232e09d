"""``/fleet``: the fleet view of the catalogue given to ``serve --catalog DIR``.

The page (``text/html``) by default; the JSON document (``imunoise.fleet.view.fleet_summary``) with
``?format=json`` or ``Accept: application/json``. The summary is computed again only when the
catalogue's parts change.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import HTMLResponse, JSONResponse

router = APIRouter(tags=["fleet"])

_cache_lock = threading.Lock()
_cache: dict[str, Any] = {}


def _summary(folder: str) -> dict[str, Any]:
    """The fleet document, recomputed when the set of parts changes."""
    from imunoise.fleet.catalog import part_paths
    from imunoise.fleet.view import fleet_summary

    parts = tuple((p.name, p.stat().st_mtime_ns) for p in part_paths(folder))
    with _cache_lock:
        if _cache.get("key") == (folder, parts):
            return _cache["doc"]
    doc = fleet_summary(folder)
    with _cache_lock:
        _cache.update(key=(folder, parts), doc=doc)
    return doc


@router.get("/fleet", response_model=None, summary="Fleet view of the catalogue")
def fleet(request: Request, format: str | None = None) -> HTMLResponse | JSONResponse:
    folder = getattr(request.app.state, "catalog", None)
    if not folder:
        raise HTTPException(404, "no fleet catalogue: start serve with --catalog DIR")
    if not Path(folder).is_dir():
        raise HTTPException(404, f"fleet catalogue {folder} does not exist (yet)")
    from imunoise.extras import MissingExtra, require

    try:
        require("fleet", "the fleet view", ("pyarrow",))
    except MissingExtra as exc:
        raise HTTPException(501, str(exc)) from None
    from imunoise.fleet.catalog import CatalogError

    try:
        doc = _summary(str(folder))
    except CatalogError as exc:
        raise HTTPException(500, str(exc)) from None
    wants_json = format == "json" or (
        format is None and "application/json" in request.headers.get("accept", "")
        and "text/html" not in request.headers.get("accept", ""))
    if wants_json:
        return JSONResponse(doc)
    from imunoise.fleet.html import render_fleet

    return HTMLResponse(render_fleet(doc))
