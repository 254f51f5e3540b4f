"""What a cell answers and what it asks.

- :class:`Queries`: the queryables ``estimator/state`` (all current ObjectEstimates),
  ``estimator/reset`` (all, one class or one object; with ``api_token`` set, the query's
  attachment must be the token) and ``estimator/nbv`` (candidate views ranked by what they
  would teach the estimator), and the same reset and ranking for the HTTP API. Replies are
  msgpack maps with ``"v": 1``; a bad request gets ``{"v": 1, "error": ...}``, never an
  exception on the transport's thread.
- :class:`InfoRequests`: a camera whose images come without camera info is asked for it (a get
  on its info key, which ``clients/camera.py`` answers), at most every ``info_request_s``.
"""

from __future__ import annotations

import hmac
import logging
import time
from collections import Counter
from collections.abc import Callable

from posefuse.service.codec import (
    DecodeError,
    NbvRequest,
    decode_nbv_request,
    decode_reset,
    encode_estimates,
    nbv_reply,
)
from posefuse.service.keys import Keys
from posefuse.service.settings import Settings

log = logging.getLogger("posefuse.daemon.queries")


class Queries:
    """The cell's queryables and the operations behind them.

    Args:
        settings: the cell's settings (``api_token``, the next-best-view bin and distances).
        keys: the cell's key space.
        worker: the :class:`~service.worker.EstimatorWorker` whose estimates are read and reset.
        sync: the :class:`~service.sync.FrameSynchronizer` (the cameras' intrinsics).
        events: the daemon's event counters (``reset_unauthorized``).
        notify: called with every reset, as an event map (the event subscribers').
    """

    def __init__(
        self,
        settings: Settings,
        keys: Keys,
        worker,
        sync,
        events: Counter,
        notify: Callable[[dict], None],
    ):
        self.settings = settings
        self.keys = keys
        self.worker = worker
        self.sync = sync
        self.events = events
        self.notify = notify

    # ------------------------------------------------------------------ operations
    def authorized(self, token: bytes | str | None) -> bool:
        """True when no api_token is set or ``token`` is it (compared in constant time)."""
        expected = self.settings.api_token
        if expected is None:
            return True
        if token is None:
            return False
        if isinstance(token, str):
            token = token.encode()
        return hmac.compare_digest(token, expected.get_secret_value().encode())

    def reset(self, class_id=None, object_id=None) -> int:
        """Forget all tracks, a class's or an object's; how many objects were removed.
        KeyError for an unknown object, ValueError for an unknown class."""
        n = self.worker.reset(class_id, object_id)
        self.notify({"v": 1, "reset": {"class_id": class_id, "object_id": object_id, "removed": n}})
        return n

    def nbv(self, request: NbvRequest) -> dict:
        """Rank candidate views (the request's, or the default hemisphere over the bin) by
        what they would teach the estimator (estimator/nbv.py). ValueError when a candidate
        has no intrinsics and no camera info is known to give them."""
        from posefuse.estimator.nbv import (
            CandidateView,
            default_candidates,
            score_candidates,
        )

        s = self.settings
        region = s.bin_region()
        camera = self.sync.camera(request.camera_id)
        needs_camera = request.candidates is None or any(
            c.camera is None for c in request.candidates
        )
        if needs_camera and camera is None:
            which = f"camera {request.camera_id!r}" if request.camera_id else "any camera"
            raise ValueError(
                f"no camera info of {which} yet: give K, width and height with each candidate"
            )
        if request.candidates is None:
            candidates = default_candidates(camera, region, tuple(s.nbv_distances))
        else:
            candidates = [
                CandidateView(c.T_world_cam, c.camera or camera) for c in request.candidates
            ]
        tracks, indices = self.worker.nbv_inputs()
        scores = score_candidates(tracks, candidates, indices, bin_region=region)
        return nbv_reply(scores, candidates, tracks, request.top_k)

    def objects_needing_views(self) -> list[str]:
        from posefuse.estimator.nbv import needs_view

        tracks = self.worker.nbv_tracks()
        return [t.key for t in tracks if not t.key.startswith("held/") and needs_view(t)]

    # ------------------------------------------------------------------ queryables
    def on_state_query(self, query) -> None:
        try:
            query.reply(self.keys.state, encode_estimates(self.worker.snapshot()))
        except Exception:
            log.exception("state query failed")

    def on_reset_query(self, query) -> None:
        try:
            attachment = query.attachment.to_bytes() if query.attachment is not None else None
            if not self.authorized(attachment):
                self.events["reset_unauthorized"] += 1
                reply = {"v": 1, "error": "unauthorized: the reset query needs the API token"}
            else:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                request = decode_reset(payload)
                removed = self.reset(request.class_id, request.object_id)
                reply = {"v": 1, "removed": removed}
        except (DecodeError, ValueError) as exc:
            reply = {"v": 1, "error": str(exc)}
        except KeyError as exc:
            reply = {"v": 1, "error": f"unknown object_id {exc.args[0]}"}
        except Exception:
            log.exception("reset query failed")
            reply = {"v": 1, "error": "internal error"}
        _reply(query, self.keys.reset, reply)

    def on_nbv_query(self, query) -> None:
        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            reply = {"v": 1, **self.nbv(decode_nbv_request(payload))}
        except (DecodeError, ValueError) as exc:
            reply = {"v": 1, "error": str(exc)}
        except Exception:
            log.exception("nbv query failed")
            reply = {"v": 1, "error": "internal error"}
        _reply(query, self.keys.nbv, reply)


def _reply(query, key: str, reply: dict) -> None:
    """Answer a queryable with a msgpack map; a failed reply is logged, never raised."""
    import msgpack

    try:
        query.reply(key, msgpack.packb(reply, use_bin_type=True))
    except Exception:
        log.exception("reply on %s failed", key)


class InfoRequests:
    """Asks cameras for their info.

    Args:
        keys: the cell's key space.
        settings: ``info_request_s`` (the least time between two requests to one camera) and
            ``max_cameras`` (bounds the table of when each was asked).
        events: the daemon's event counters (``info_requests``, ``info_replies``).
        session: gives the open Zenoh session, or None while there is none.
        receive: takes a reply as a received message (key, payload).
    """

    def __init__(
        self,
        keys: Keys,
        settings: Settings,
        events: Counter,
        session: Callable[[], object],
        receive: Callable[[str, bytes], object],
    ):
        self.keys = keys
        self.settings = settings
        self.events = events
        self.session = session
        self.receive = receive
        self._asked: dict[str, float] = {}  # camera id -> when (monotonic s)

    def request(self, cam_id: str) -> None:
        """Ask a camera for its info (a get on its info key), at most every info_request_s."""
        session = self.session()
        now = time.monotonic()
        if session is None or now - self._asked.get(cam_id, -1e9) < (self.settings.info_request_s):
            return
        if len(self._asked) > 4 * self.settings.max_cameras:
            self._asked.clear()
        self._asked[cam_id] = now
        self.events["info_requests"] += 1
        try:
            session.get(self.keys.camera(cam_id, "info"), self.on_reply, timeout=2.0)
        except Exception:
            log.exception("camera info request for %s failed", cam_id)

    def request_all(self, session) -> None:
        """Ask every camera already running for its info rather than wait for it."""
        try:
            session.get(f"{self.keys.root}/cam/*/info", self.on_reply, timeout=2.0)
        except Exception:
            log.exception("asking the cameras for their info failed")

    def on_reply(self, reply) -> None:
        try:
            ok = reply.ok
            if ok is not None:
                self.events["info_replies"] += 1
                self.receive(str(ok.key_expr), ok.payload.to_bytes())
        except Exception:
            log.exception("camera info reply")
