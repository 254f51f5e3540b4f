"""The HTTP API, in the daemon's process: thin routes over the daemon's snapshot and counters.

Errors become HTTP codes here only: an unknown object 404, a bad reset request 422.
"""

from __future__ import annotations

import asyncio
import json
import queue

from fastapi import FastAPI, HTTPException
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, Field, model_validator

from service.codec import estimate_to_dict

EXAMPLE_ESTIMATE = {
    "v": 1,
    "stamp_ns": 1_700_000_000_000_000_000,
    "object_id": "gear-001",
    "class_id": 4,
    "class_name": "gear",
    "frame_id": "world",
    "t": [0.031, -0.012, 0.018],
    "q": [0.0, 0.0, 0.3826834, 0.9238795],
    "cov": [0.0] * 36,
    "confidence": 0.71,
    "hypotheses": [{"q": [0.0, 0.0, 0.3826834, 0.9238795], "weight": 0.9, "n": 5}],
    "n_views": 6,
    "status": "confirmed",
}


class ObjectEstimateModel(BaseModel):
    """One object's pose estimate (the ObjectEstimate of the wire protocol)."""

    v: int = 1
    stamp_ns: int
    object_id: str
    class_id: int
    class_name: str
    frame_id: str = "world"
    t: list[float] = Field(description="T_world_obj translation, metres")
    q: list[float] = Field(description="T_world_obj rotation, quaternion [x, y, z, w]")
    cov: list[float] = Field(description="6x6 row-major, x y z rot_x rot_y rot_z")
    confidence: float
    hypotheses: list[dict]
    n_views: int
    status: str

    model_config = {"json_schema_extra": {"examples": [EXAMPLE_ESTIMATE]}}


class ResetRequestModel(BaseModel):
    """Reset everything (empty body), one class, or one object."""

    class_id: int | None = None
    object_id: str | None = None

    @model_validator(mode="after")
    def _one(self):
        if self.class_id is not None and self.object_id is not None:
            raise ValueError("give class_id or object_id, not both")
        return self

    model_config = {
        "json_schema_extra": {"examples": [{}, {"class_id": 4}, {"object_id": "gear-001"}]}
    }


class ResetResponse(BaseModel):
    removed: int


def _serve_docs_locally(app: FastAPI) -> None:
    """``/docs``: Swagger UI from the ``swagger-ui-bundle`` package, not from a CDN."""
    import swagger_ui_bundle
    from fastapi.openapi.docs import get_swagger_ui_html
    from fastapi.staticfiles import StaticFiles

    app.mount(
        "/docs-assets",
        StaticFiles(directory=swagger_ui_bundle.swagger_ui_path),
        name="docs-assets",
    )

    @app.get("/docs", include_in_schema=False)
    def docs():
        return get_swagger_ui_html(
            openapi_url=app.openapi_url,
            title="posefuse API",
            swagger_js_url="/docs-assets/swagger-ui-bundle.js",
            swagger_css_url="/docs-assets/swagger-ui.css",
            swagger_favicon_url="/docs-assets/favicon-32x32.png",
        )


def create_app(daemon) -> FastAPI:
    """The API of one daemon (anything with worker, stats_dict, reset, subscribe, ready)."""
    app = FastAPI(
        title="posefuse",
        description="Multi-view 6D poses of textureless parts: current estimates, reset, stats.",
        version="1",
        docs_url=None,  # served below from local assets: a cell is often offline
        redoc_url=None,
    )
    _serve_docs_locally(app)

    @app.get("/healthz", summary="The process is alive")
    def healthz() -> dict:
        return {"status": "ok"}

    @app.get("/readyz", summary="The Zenoh session is open and the estimator is ready")
    def readyz() -> dict:
        if not daemon.ready.is_set():
            raise HTTPException(status_code=503, detail="not ready")
        return {"status": "ready"}

    @app.get("/objects", response_model=list[ObjectEstimateModel], summary="All current estimates")
    def objects() -> list[dict]:
        return [estimate_to_dict(e) for e in daemon.worker.snapshot()]

    @app.get("/objects/{object_id}", response_model=ObjectEstimateModel, summary="One object")
    def one(object_id: str) -> dict:
        e = daemon.worker.get(object_id)
        if e is None:
            raise HTTPException(status_code=404, detail=f"no object {object_id!r}")
        return estimate_to_dict(e)

    @app.post("/reset", response_model=ResetResponse, summary="Forget all, a class, or an object")
    def reset(request: ResetRequestModel | None = None) -> dict:
        request = request or ResetRequestModel()
        try:
            return {"removed": daemon.reset(request.class_id, request.object_id)}
        except KeyError:
            raise HTTPException(
                status_code=404, detail=f"no object {request.object_id!r}"
            ) from None
        except ValueError as exc:
            raise HTTPException(status_code=422, detail=str(exc)) from None

    @app.get("/stats", summary="Frames received, processed, dropped; decode errors; latency")
    def stats() -> dict:
        return daemon.stats_dict()

    @app.get("/events", summary="Server-Sent Events: one 'estimate' event per pose update")
    async def events(max_events: int = 0) -> StreamingResponse:
        q = daemon.subscribe()

        async def stream():
            sent = 0
            try:
                yield ": posefuse estimate stream\n\n"
                while max_events <= 0 or sent < max_events:
                    try:
                        item = q.get_nowait()
                    except queue.Empty:
                        await asyncio.sleep(0.02)
                        continue
                    kind = "reset" if "reset" in item else "estimate"
                    yield f"event: {kind}\ndata: {json.dumps(item)}\n\n"
                    sent += 1
            finally:
                daemon.unsubscribe(q)

        return StreamingResponse(stream(), media_type="text/event-stream")

    return app
