"""The tracks as plain picklable data, and back (the service's snapshots keep them on disk).

Version 3 keeps a track's views as typed records (:class:`~estimator.tracker.tracks.ViewRef`,
:class:`~estimator.tracker.tracks.PendingView`, :class:`~estimator.tracker.tracks.DetectionRef`).
Version 2, written before the estimator's modules were grouped by the method's steps, kept
them as plain tuples and named its classes by their old modules (``posefuse.estimator.mixture``
and so on): :func:`legacy_class` finds such a class where it lives now, and :func:`upgrade`
turns the tuples into records, so a daemon restarted on a new version goes on where it was.
"""

from __future__ import annotations

import importlib

from posefuse.estimator.tracker.tracks import DetectionRef, PendingView, Track, ViewRef

STATE_VERSION = 3  # 3: typed view records; 2: tuples, the flat module layout

# where the classes of a version 2 state live now (old module -> new modules, first hit wins)
LEGACY_MODULES: dict[str, tuple[str, ...]] = {
    "posefuse.estimator.translation": ("posefuse.estimator.translation.gaussian",),
    "posefuse.estimator.founding": ("posefuse.estimator.translation.founding",),
    "posefuse.estimator.association": ("posefuse.estimator.translation.association",),
    "posefuse.estimator.mixture": ("posefuse.estimator.rotation.mixture",),
    "posefuse.estimator.rotation": ("posefuse.estimator.rotation.matching",),
    "posefuse.estimator.edges": (
        "posefuse.estimator.verification.model_edges",
        "posefuse.estimator.verification.edge_maps",
    ),
    "posefuse.estimator.verification": ("posefuse.estimator.verification.verify",),
    "posefuse.estimator.refinement": ("posefuse.estimator.verification.refinement",),
    "posefuse.estimator.geometry": ("posefuse.estimator.core.geometry",),
    "posefuse.estimator.camera": ("posefuse.estimator.core.camera",),
    "posefuse.estimator.symmetry": ("posefuse.estimator.core.symmetry",),
    "posefuse.estimator.tracker": ("posefuse.estimator.tracker.tracks",),
}


def legacy_class(module: str, name: str):
    """The class a version 2 state names ``module.name``, where it lives now; None if no
    module of :data:`LEGACY_MODULES` has it."""
    for candidate in LEGACY_MODULES.get(module, ()):
        try:
            found = getattr(importlib.import_module(candidate), name, None)
        except ImportError:
            continue
        if found is not None:
            return found
    return None


def export_state(tracks: dict[str, Track], book, size_ratios: dict, last_stamp_ns) -> dict:
    """The tracks and the counters that go with them (see ``MultiViewEstimator.export_state``)."""
    return {
        "version": STATE_VERSION,
        "tracks": tracks,
        "serial": book.serial,
        "size_ratios": size_ratios,
        "held": book.held,
        "view_serial": book.view_serial,
        "last_stamp_ns": last_stamp_ns,
    }


def upgrade(state: dict) -> dict:
    """A version 2 or 3 state as version 3 (version 2's view tuples become records; the
    tracks are changed in place); ValueError for any other."""
    if not isinstance(state, dict) or state.get("version") not in (2, STATE_VERSION):
        raise ValueError(f"estimator state: version must be 2 or {STATE_VERSION}")
    if state["version"] == 2:
        for track in state["tracks"].values():
            track.refs = [ViewRef(*r) for r in track.refs]
            track.pending = [PendingView(*p) for p in track.pending]
            track.detections = [DetectionRef(*d) for d in track.detections]
        state = {**state, "version": STATE_VERSION}
    return state
