"""Which daemon produces a cell's estimates: decided by Zenoh liveliness tokens.

Every daemon that may serve a cell declares a *member* token
``{cell}/@v1/estimator/member/{rank}/{zid}`` (rank 0: the cell is one of its ``cells``; rank
1: one of its ``standby_cells``; ``zid`` its Zenoh session id). The daemon that serves the
cell declares the *active* token ``{cell}/@v1/estimator/active/{zid}``. Each daemon follows
both sets with a liveliness subscriber (history on) and decides every ``interval_s``:

- it is active: if another daemon is active too with a smaller ``zid`` (two started at the
  same moment, or a partition healed), it steps down;
- another daemon is active: it stands by (no subscriptions, no CPU);
- no daemon is active: it claims the cell when it is eligible and its ``(rank, zid)`` is the
  smallest among the members. A primary is always eligible; a standby once it has seen an
  active daemon disappear, or ``grace_s`` after its start (so the cell's primary, started at
  the same time, wins; and a cell whose primary never comes is still served).

A running active daemon is never preempted. When its process dies its tokens vanish (the
router notices a closed session at once, a lost link after Zenoh's lease, 10 s by default),
and a standby takes over from the last state snapshot in the shared ``state_dir``.

Pure bookkeeping in :class:`ElectionState` (tested without Zenoh); :class:`Election` wires it
to a session.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

log = logging.getLogger("posefuse.election")

PRIMARY, STANDBY = 0, 1


@dataclass
class ElectionState:
    """The tokens seen and the decision rule (see the module docstring)."""

    zid: str
    rank: int
    grace_s: float
    started: float
    active: bool = False
    seen_active: bool = False
    actives: set[str] = field(default_factory=set)
    members: set[tuple[int, str]] = field(default_factory=set)

    def observe(self, kind: str, zid: str, rank: int | None, present: bool) -> None:
        """A token appeared (``present``) or vanished: kind ``active`` or ``member``."""
        if kind == "active":
            if present:
                self.actives.add(zid)
                if zid != self.zid:
                    self.seen_active = True
            else:
                self.actives.discard(zid)
        elif kind == "member" and rank is not None:
            (self.members.add if present else self.members.discard)((rank, zid))

    def decide(self, now: float) -> str | None:
        """``activate``, ``deactivate`` or None (no change)."""
        others = self.actives - {self.zid}
        if self.active:
            if others and min(others) < self.zid:
                return "deactivate"
            return None
        if others:
            return None
        eligible = self.rank == PRIMARY or self.seen_active or now - self.started >= self.grace_s
        if not eligible:
            return None
        if min(self.members | {(self.rank, self.zid)}) == (self.rank, self.zid):
            return "activate"
        return None


class Election:
    """One cell's election on a session; calls ``activate()`` / ``deactivate()`` of the cell.

    Args:
        session: an open zenoh.Session. root: the cell's key root ``{cell}/@v1``.
        primary: the cell is one of the daemon's ``cells`` (else a standby cell).
    """

    def __init__(
        self,
        session,
        root: str,
        primary: bool,
        grace_s: float,
        activate,
        deactivate,
        interval_s: float = 0.2,
    ):
        self.session = session
        self.root = root
        self.zid = str(session.zid())
        self.state = ElectionState(
            self.zid, PRIMARY if primary else STANDBY, grace_s, time.monotonic()
        )
        self._activate, self._deactivate = activate, deactivate
        self.interval_s = interval_s
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._active_token = None
        self._member_token = None
        self._subscriber = None
        self._thread = threading.Thread(target=self._loop, daemon=True, name=f"election-{root}")
        self.transitions: list[tuple[float, str]] = []

    @property
    def active(self) -> bool:
        return self.state.active

    def _on_token(self, sample) -> None:
        try:
            import zenoh

            parts = str(sample.key_expr)[len(self.root) + 1 :].split("/")
            present = sample.kind == zenoh.SampleKind.PUT
            with self._lock:
                if len(parts) == 3 and parts[:2] == ["estimator", "active"]:
                    self.state.observe("active", parts[2], None, present)
                elif len(parts) == 4 and parts[:2] == ["estimator", "member"]:
                    self.state.observe("member", parts[3], int(parts[2]), present)
        except Exception:  # a malformed token key is ignored, never fatal
            log.exception("liveliness token %s", sample.key_expr)

    def start(self, settle_s: float = 1.0) -> None:
        """Declare membership, learn the tokens that exist, decide once, then keep deciding."""
        liveliness = self.session.liveliness()
        self._member_token = liveliness.declare_token(
            f"{self.root}/estimator/member/{self.state.rank}/{self.zid}"
        )
        self._subscriber = liveliness.declare_subscriber(
            f"{self.root}/estimator/**", self._on_token, history=True
        )
        # the tokens that exist now (a get returns once every peer or the router answered)
        for reply in liveliness.get(f"{self.root}/estimator/**", timeout=settle_s):
            if reply.ok is not None:
                self._on_token(reply.ok)
        self.step()
        self._thread.start()

    def step(self) -> None:
        with self._lock:
            decision = self.state.decide(time.monotonic())
        if decision == "activate":
            self._activate()
            self._active_token = self.session.liveliness().declare_token(
                f"{self.root}/estimator/active/{self.zid}"
            )
            with self._lock:
                self.state.active = True
                self.state.actives.add(self.zid)
        elif decision == "deactivate":
            if self._active_token is not None:
                self._active_token.undeclare()
                self._active_token = None
            with self._lock:
                self.state.active = False
                self.state.actives.discard(self.zid)
            self._deactivate()
        if decision:
            self.transitions.append((time.monotonic(), decision))
            log.info("%s: %s (%s)", self.root, decision, self.zid)

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.step()
            except Exception:
                log.exception("election of %s", self.root)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        for entity in (self._active_token, self._subscriber, self._member_token):
            if entity is not None:
                try:
                    entity.undeclare()
                except Exception:
                    log.exception("undeclaring an election entity")
