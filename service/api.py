"""The HTTP API, in the daemon's process: thin routes over the daemon's snapshot and counters.

Errors become HTTP codes here only, and every code a route can give is in the OpenAPI document:
an unknown object 404, a body that is not UTF-8 JSON 400, a JSON body that does not match the
schema 422 (non-finite numbers, booleans for integers and unknown fields included), a missing or
wrong API token 401 (counted in the daemon's ``events``), a body over ``max_body_bytes`` 413.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import math
import queue
import threading
from typing import Annotated

from fastapi import Depends, FastAPI, HTTPException, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StrictInt, model_validator

from posefuse.service.codec import estimate_to_dict

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
    "verified": True,
    "ambiguity": 0.0,
    "alternatives": [],
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
    verified: bool = Field(
        False,
        description="the pose is the one the object's views agree on (verified across them and "
        "refined); false while that check waits for the newest views, and without verification",
    )
    ambiguity: float = Field(
        0.0,
        description="the largest odds, in [0, 1], of a near-symmetric turn of the rotation "
        "against it, as the verified views judge it (0: none, or each ruled out plainly)",
    )
    alternatives: list[dict] = Field(
        default_factory=list,
        description="the near-symmetric turns the views cannot rule out, most likely first: "
        "{q: the alternative rotation [x, y, z, w], odds}; not empty means ambiguous, and the "
        "rotation covariance then covers each",
    )

    model_config = {"json_schema_extra": {"examples": [EXAMPLE_ESTIMATE]}}


def _integral_number(value):
    """A float with no fractional part as the integer it is (JSON Schema's ``integer``);
    anything else as it came, for StrictInt to judge."""
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        return int(value)
    return value


class ResetRequestModel(BaseModel):
    """Reset everything (empty body), one class, or one object."""

    # omitted, not null; an integer, not a bool, a string or a fraction. A JSON number with no
    # fractional part (4.0) is an integer to JSON Schema, and so to the OpenAPI document
    class_id: Annotated[StrictInt, BeforeValidator(_integral_number)] = Field(
        None, ge=1, le=2**31 - 1
    )
    object_id: str = Field(None, min_length=1, max_length=256)

    @model_validator(mode="after")
    def _one(self):
        if self.class_id is not None and self.object_id is not None:
            raise ValueError("give class_id or object_id, not both")
        return self

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [{}, {"class_id": 4}, {"object_id": "gear-001"}],
            "not": {"required": ["class_id", "object_id"]},
        },
    )


class ResetResponse(BaseModel):
    removed: int


class NbvCandidateModel(BaseModel):
    """A camera pose the robot can reach; K, width and height when it is not the camera's."""

    T_world_cam: list[float] = Field(min_length=16, max_length=16, description="row-major 4x4")
    K: list[float] | None = Field(None, min_length=9, max_length=9, description="row-major 3x3")
    width: StrictInt | None = Field(None, ge=1, le=65535)
    height: StrictInt | None = Field(None, ge=1, le=65535)
    model_config = ConfigDict(extra="forbid")


class NbvRequestModel(BaseModel):
    """Candidates to rank (omitted: a hemisphere over the bin at the working distances)."""

    # at most 1000 (checked with the rest of the request, 422); the body's size limit
    # (POSEFUSE_MAX_BODY_BYTES, 64 KiB: about 100 candidates) applies first (413)
    candidates: list[NbvCandidateModel] | None = Field(None, min_length=1)
    camera_id: str | None = Field(None, min_length=1, max_length=256)
    top_k: StrictInt = Field(10, ge=1, le=1000)
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {},
                {
                    "top_k": 1,
                    "candidates": [
                        {"T_world_cam": [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0.7, 0, 0, 0, 1]}
                    ],
                },
            ]
        },
    )


class NbvObjectGain(BaseModel):
    object_id: str
    translation_gain: float = Field(description="nats")
    rotation_gain: float = Field(description="nats")
    visibility: float = Field(description="0 (hidden or outside the image) to 1")


class NbvRanked(BaseModel):
    index: int = Field(description="the candidate's index in the request")
    score: float = Field(description="expected information, nats")
    T_world_cam: list[float]
    objects: list[NbvObjectGain]


class NbvResponse(BaseModel):
    candidates: int
    ranked: list[NbvRanked]


class ErrorModel(BaseModel):
    """An error: what went wrong, in words."""

    detail: str


class ValidationIssue(BaseModel):
    loc: list[str | int]
    msg: str
    type: str


class ValidationErrorModel(BaseModel):
    """A request that does not match the schema: one entry per problem."""

    detail: list[ValidationIssue]


def _error(description: str, model=ErrorModel) -> dict:
    return {"model": model, "description": description}


INVALID = {422: _error("The request does not match the schema", ValidationErrorModel)}
TOO_LARGE = {413: _error("The request body is larger than max_body_bytes")}
UNAUTHORIZED = {401: _error("The API token is set and the request does not carry it")}


class BodySizeLimit:
    """ASGI middleware: a request body over ``max_bytes`` gets 413 before a route reads it,
    by its Content-Length or, when it has none, by reading it first (bodies here are small)."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers", []))
        if b"content-length" in headers:
            try:
                too_large = int(headers[b"content-length"]) > self.max_bytes
            except ValueError:
                too_large = True
            if too_large:
                return await self._refuse(send)
            return await self.app(scope, receive, send)
        if scope.get("method") in ("GET", "HEAD", "OPTIONS"):
            return await self.app(scope, receive, send)
        messages, size = [], 0
        while True:
            message = await receive()
            messages.append(message)
            if message["type"] != "http.request":
                break
            size += len(message.get("body", b""))
            if size > self.max_bytes:
                return await self._refuse(send)
            if not message.get("more_body", False):
                break

        async def replay():
            return messages.pop(0) if messages else await receive()

        await self.app(scope, replay, send)

    async def _refuse(self, send):
        body = json.dumps({"detail": f"request body over {self.max_bytes} bytes"}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [(b"content-type", b"application/json")],
            }
        )
        await send({"type": "http.response.body", "body": body})


BearerCredentials = Annotated[
    HTTPAuthorizationCredentials | None,
    Depends(HTTPBearer(auto_error=False, description="POSEFUSE_API_TOKEN")),
]


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """400 for a body that cannot be parsed (not JSON, not UTF-8), else 422 with the documented
    shape; the offending input is not echoed back (it may be huge or not representable in JSON,
    as NaN is)."""
    errors = exc.errors()
    unparsable = [e for e in errors if e.get("type") == "json_invalid"]
    if unparsable:
        where = unparsable[0].get("ctx", {}).get("error", "invalid JSON")
        return JSONResponse(
            status_code=400, content={"detail": f"the body is not UTF-8 JSON ({where})"}
        )
    detail = [
        {
            "loc": [_json_safe(x) if isinstance(x, (int, str)) else str(x) for x in e["loc"]],
            "msg": str(e.get("msg", "")),
            "type": str(e.get("type", "")),
        }
        for e in errors
    ]
    return JSONResponse(status_code=422, content={"detail": detail})


async def _http_error(request: Request, exc: HTTPException) -> JSONResponse:
    return JSONResponse(
        status_code=exc.status_code, content={"detail": str(exc.detail)}, headers=exc.headers
    )


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


def create_cells_app(cells, closing: threading.Event | None = None) -> FastAPI:
    """The API of a process serving several cells: the first cell's routes at ``/``, every
    cell's at ``/cells/{cell}/`` (one cell: the plain API, with that mount too); one
    ``closing`` for all of them (see :func:`create_app`)."""
    closing = closing or threading.Event()
    first = next(iter(cells.daemons.values()))
    app = create_app(first, closing)
    for cell, daemon in cells.daemons.items():
        app.mount(f"/cells/{cell}", create_app(daemon, closing))
    return app


def begin_closing(app) -> None:
    """Tell the app's open event streams that the server is stopping: each ends within one
    poll (20 ms), so that a stop waits for no stream and cancels none."""
    closing = getattr(getattr(app, "state", None), "closing", None)
    if closing is not None:
        closing.set()


def create_app(daemon, closing: threading.Event | None = None) -> FastAPI:
    """The API of one daemon (anything with settings, worker, stats_dict, reset, subscribe,
    ready). ``closing``, once set (:func:`begin_closing`), ends the open ``/events`` streams."""
    closing = closing or threading.Event()
    settings = daemon.settings
    token = settings.api_token.get_secret_value() if settings.api_token else None
    app = FastAPI(
        title="posefuse",
        description="Multi-view 6D poses of textureless parts: current estimates, reset, stats."
        + (" Mutating routes need `Authorization: Bearer <POSEFUSE_API_TOKEN>`." if token else ""),
        version="1",
        docs_url=None,  # served below from local assets: a cell is often offline
        redoc_url=None,
        exception_handlers={
            RequestValidationError: _validation_error,
            HTTPException: _http_error,
        },
    )
    app.state.closing = closing
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    _serve_docs_locally(app)

    def require_token(request: Request, credentials: BearerCredentials) -> None:
        if token is None:
            return
        given = credentials.credentials.encode() if credentials else b""
        if not hmac.compare_digest(given, token.encode()):
            events = getattr(daemon, "events", None)
            if events is not None:
                events["http_unauthorized"] += 1
                if request.url.path.endswith("/reset"):
                    events["reset_unauthorized"] += 1
            raise HTTPException(
                status_code=401,
                detail="missing or wrong API token",
                headers={"WWW-Authenticate": "Bearer"},
            )

    guard = [Depends(require_token)] if token else []
    events_guard = guard if settings.protect_events else []

    @app.get("/healthz", summary="The process is alive")
    def healthz() -> dict:
        return {"status": "ok"}

    @app.get(
        "/readyz",
        summary="The Zenoh session is open and the estimator is ready",
        responses={503: _error("Not ready yet (or stopping)")},
    )
    def readyz() -> dict:
        if not daemon.ready.is_set():
            raise HTTPException(status_code=503, detail="not ready")
        return {"status": "ready", "role": "active" if daemon.active else "standby"}

    @app.get("/objects", response_model=list[ObjectEstimateModel], summary="All current estimates")
    def objects() -> list[dict]:
        return [estimate_to_dict(e) for e in daemon.worker.snapshot()]

    @app.get(
        "/objects/{object_id}",
        response_model=ObjectEstimateModel,
        summary="One object",
        responses={404: _error("No object with this id")},
    )
    def one(object_id: str) -> dict:
        e = daemon.worker.get(object_id)
        if e is None:
            raise HTTPException(status_code=404, detail=f"no object {object_id!r}")
        return estimate_to_dict(e)

    @app.post(
        "/reset",
        response_model=ResetResponse,
        summary="Forget all, a class, or an object",
        dependencies=guard,
        responses={
            400: _error("The body cannot be parsed (not UTF-8 JSON)"),
            404: _error("No object with this id, or no class with this id in the catalog"),
            **INVALID,
            **TOO_LARGE,
            **(UNAUTHORIZED if token else {}),
        },
    )
    def reset(request: ResetRequestModel | None = None) -> dict:
        request = request or ResetRequestModel()
        try:
            return {"removed": daemon.reset(request.class_id, request.object_id)}
        except KeyError:
            raise HTTPException(
                status_code=404, detail=f"no object {request.object_id!r}"
            ) from None
        except ValueError as exc:  # a class the catalog does not have
            raise HTTPException(status_code=404, detail=str(exc)) from None

    @app.post(
        "/nbv",
        response_model=NbvResponse,
        summary="Rank candidate camera poses by what they would teach the estimator",
        dependencies=guard,
        responses={
            400: _error("The body cannot be parsed (not UTF-8 JSON)"),
            409: _error("Candidates without intrinsics and no camera info known yet"),
            **INVALID,
            **TOO_LARGE,
            **(UNAUTHORIZED if token else {}),
        },
    )
    def nbv(request: NbvRequestModel | None = None):
        from posefuse.service.codec import DecodeError, nbv_request_from_dict

        body = (request or NbvRequestModel()).model_dump(exclude_none=True)
        for c in body.get("candidates", []):
            for k in [k for k, v in c.items() if v is None]:
                del c[k]
        try:
            parsed = nbv_request_from_dict(body)
        except DecodeError as exc:  # as the schema's own 422s: a list of issues
            issue = {"loc": ["body", "candidates"], "msg": str(exc), "type": "value_error"}
            return JSONResponse(status_code=422, content={"detail": [issue]})
        try:
            return daemon.nbv(parsed)
        except ValueError as exc:
            raise HTTPException(status_code=409, detail=str(exc)) from None

    @app.get("/stats", summary="Frames received, processed, dropped; decode errors; latency")
    def stats() -> dict:
        return daemon.stats_dict()

    @app.get(
        "/events",
        summary="Server-Sent Events: one 'estimate' event per pose update",
        response_class=StreamingResponse,
        dependencies=events_guard,
        responses={
            200: {
                "description": "An endless event stream (or max_events events)",
                "content": {"text/event-stream": {"schema": {"type": "string"}}},
            },
            **INVALID,
            **(UNAUTHORIZED if events_guard else {}),
        },
    )
    async def events(
        max_events: int = Query(0, ge=0, le=1_000_000, description="stop after N, 0: never"),
    ) -> StreamingResponse:
        q = daemon.subscribe()

        async def stream():
            sent = 0
            try:
                yield ": posefuse estimate stream\n\n"
                while (max_events <= 0 or sent < max_events) and not closing.is_set():
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
