"""A contact sheet of one part: three renders with its symmetry axes drawn and the detection's
numbers beside them, for a person to confirm or override (``posefuse onboard --symmetry``).

Claimed axes are green (continuous: a double line), alternatives not claimed orange; a flagged
part (a claim near the tolerance, or an alternative) says so in red. Where the part keeps a
near-symmetry (an alternative not claimed), the edges that tell its turns apart, which the
daemon judges them by (:mod:`estimator.verification.turns`), are drawn as orange dots where they
show: a camera must see them for the turn to be known.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.objects import ObjectModel
from posefuse.estimator.core.symmetry import SymmetryReport, _surface_moments
from posefuse.estimator.rotation.render import DEFAULT_LIGHTING, Renderer
from posefuse.estimator.rotation.templates import look_at_rotation

PANEL = 320  # pixels per render
TEXT_WIDTH = 560
GREEN, ORANGE, RED, WHITE = (60, 200, 60), (0, 150, 255), (40, 40, 230), (235, 235, 235)
# view directions (object -> camera): two obliques and one along the object's z
VIEWS = ((1.0, -1.2, 0.9), (-1.1, -0.4, 1.2), (0.05, 0.02, 1.0))


def _camera(diameter: float) -> tuple[Camera, float]:
    focal = 2.2 * PANEL
    distance = focal * diameter / (0.75 * PANEL)  # the diameter spans 75% of the panel
    c = (PANEL - 1) / 2.0
    return Camera(np.array([[focal, 0, c], [0, focal, c], [0, 0, 1.0]]), PANEL, PANEL), distance


def render_contact_sheet(model: ObjectModel, report: SymmetryReport) -> np.ndarray:
    """(H, W, 3) uint8 BGR: three views of ``model`` with the axes of ``report``."""
    camera, distance = _camera(model.diameter)
    center, _ = _surface_moments(model.mesh)
    renderer = Renderer([model.mesh])
    distinct = distinguishing_edges(model)
    panels = []
    for view in VIEWS:
        v = np.asarray(view) / np.linalg.norm(view)
        T_cam_obj = np.eye(4)
        T_cam_obj[:3, :3] = look_at_rotation(v)
        T_cam_obj[:3, 3] = [0.0, 0.0, distance] - T_cam_obj[:3, :3] @ center
        result = renderer.render(camera, np.linalg.inv(T_cam_obj), DEFAULT_LIGHTING, shadows=False)
        image = np.ascontiguousarray(cv2.cvtColor(result.image, cv2.COLOR_RGB2BGR))
        for axes, colour, at_start in (
            (report.alternatives, ORANGE, True),
            (report.axes, GREEN, False),
        ):
            for axis in axes:
                _draw_axis(
                    image,
                    camera,
                    T_cam_obj,
                    center,
                    np.asarray(axis.axis),
                    axis.order,
                    model.diameter,
                    colour,
                    at_start,
                )
        if distinct is not None:
            _draw_samples(image, camera, T_cam_obj, distinct)
        panels.append(image)
    text = np.zeros((PANEL, TEXT_WIDTH, 3), np.uint8)
    lines = [
        (f"{model.name}  (obj {model.obj_id}, diameter {model.diameter * 1000:.1f} mm)", WHITE)
    ]
    lines.append((f"claimed: {report.describe()}", GREEN))
    for axis in report.axes:
        lines.append(
            (
                f"  {axis.name()}: residual {100 * axis.residual:.2f}%, margin "
                f"{100 * report.margin(axis):.2f}% of d",
                GREEN,
            )
        )
    for axis in report.alternatives:
        lines.append((f"  alternative {axis.name()}: residual {100 * axis.residual:.2f}%", ORANGE))
    lines.append(
        (f"tolerance {100 * report.tol_frac:.1f}% of d (95th pct surface distance)", WHITE)
    )
    if model.near_symmetries:
        if distinct is None:
            lines.append(("no edge tells its near-symmetric turns apart: all published", ORANGE))
        else:
            lines.append(
                (f"{len(distinct.points)} edge samples tell its turns apart (orange dots)", ORANGE)
            )
    if report.flags:
        lines.append(("FLAGGED - please decide:", RED))
        for flag in report.flags:
            lines += [(f"  {chunk}", RED) for chunk in _wrap(flag, 62)]
        lines.append((f"  e.g. --symmetry {model.name}=continuous | N:z | none", RED))
    for k, (line, colour) in enumerate(lines[:17]):
        cv2.putText(
            text, line, (10, 24 + 17 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.42, colour, 1, cv2.LINE_AA
        )
    return np.hstack(panels + [text])


def write_contact_sheet(model: ObjectModel, report: SymmetryReport, out: str | Path) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), render_contact_sheet(model, report))
    return out


def distinguishing_edges(model: ObjectModel, config=None):
    """The edge samples the daemon judges the turns of ``model``'s near-symmetries by
    (:func:`estimator.verification.turns.distinct_edges` of the turns the verification does not
    ask about, as ``PoseStage.model_edges`` makes them), or None: no near-symmetry, or no edge
    that tells its turns apart. ``config``: a VerificationConfig (default: the default one)."""
    from posefuse.estimator.verification.turns import distinct_edges
    from posefuse.estimator.verification.verify import (
        VerificationConfig,
        near_symmetries,
        near_symmetry_turns,
    )

    if not model.near_symmetries:
        return None
    config = config or VerificationConfig()
    sym = np.concatenate([np.eye(3)[None], model.symmetries_discrete[:, :3, :3]])
    axes = np.array([c.axis for c in model.symmetries_continuous]).reshape(-1, 3)
    variants = near_symmetries(
        model.points, model.diameter, sym, axes, config.near_frac, config.max_variants
    )
    turns = near_symmetry_turns(
        np.array([g.axis for g in model.near_symmetries]).reshape(-1, 3),
        np.array([g.order for g in model.near_symmetries], int),
        sym,
        axes,
        variants,
    )
    if not len(turns):
        return None
    return distinct_edges(model.mesh, model.diameter, turns, config.edges, config.turns)


def _draw_samples(image, camera, T_cam_obj, edges) -> None:
    """The samples of ``edges`` that show from the panel's camera (on its occluding contour or
    a visible crease, not hidden by the part), as orange dots."""
    from posefuse.estimator.verification.model_edges import pose_edges

    R, t = T_cam_obj[None, :3, :3], T_cam_obj[None, :3, 3]
    _, _, active, _ = pose_edges(edges, R, t, False)
    pts = edges.points[active[0]] @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    for u, v in camera.project(pts):
        if np.isfinite(u) and np.isfinite(v):
            cv2.circle(image, (int(round(u)), int(round(v))), 2, ORANGE, -1, cv2.LINE_AA)


def _draw_axis(image, camera, T_cam_obj, center, axis, order, diameter, colour, at_start):
    ends = np.stack([center - 0.65 * diameter * axis, center + 0.65 * diameter * axis])
    pts_cam = ends @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    uv = camera.project(pts_cam)
    if not np.all(np.isfinite(uv)):
        return
    p0, p1 = (tuple(int(round(c)) for c in p) for p in uv)
    cv2.line(image, p0, p1, colour, 2, cv2.LINE_AA)
    if order == 0:  # continuous: a second, thin line beside it
        d = np.asarray(p1, float) - np.asarray(p0, float)
        n = np.array([-d[1], d[0]]) / max(np.linalg.norm(d), 1e-9) * 4
        cv2.line(
            image,
            tuple((np.asarray(p0) + n).astype(int)),
            tuple((np.asarray(p1) + n).astype(int)),
            colour,
            1,
            cv2.LINE_AA,
        )
    label = "inf" if order == 0 else str(order)
    where = p0 if at_start else p1  # alternatives label the other end of a shared axis
    cv2.putText(
        image,
        label,
        (where[0] + 4, where[1]),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.5,
        colour,
        1,
        cv2.LINE_AA,
    )


def _wrap(text: str, width: int) -> list[str]:
    words, lines, line = text.split(), [], ""
    for word in words:
        if len(line) + len(word) + 1 > width and line:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return lines + [line] if line else lines


FAMILY_PANEL = 160  # pixels per shape in a family's picture
FAMILY_COLUMNS = 10


def render_family_sheet(catalog, limit: int = 100) -> np.ndarray:
    """(H, W, 3) uint8 BGR: the first ``limit`` shapes of a catalog, one oblique view each, each
    filling its panel, with its obj_id and name."""
    ids = sorted(catalog)[:limit]
    focal = 2.2 * FAMILY_PANEL
    c = (FAMILY_PANEL - 1) / 2.0
    camera = Camera(
        np.array([[focal, 0, c], [0, focal, c], [0, 0, 1.0]]), FAMILY_PANEL, FAMILY_PANEL
    )
    v = np.asarray(VIEWS[0]) / np.linalg.norm(VIEWS[0])
    panels = []
    for obj_id in ids:
        model = catalog[obj_id]
        distance = focal * model.diameter / (0.85 * FAMILY_PANEL)
        T_cam_obj = np.eye(4)
        T_cam_obj[:3, :3] = look_at_rotation(v)
        T_cam_obj[:3, 3] = [0.0, 0.0, distance]
        result = Renderer([model.mesh]).render(
            camera, np.linalg.inv(T_cam_obj), DEFAULT_LIGHTING, shadows=False
        )
        image = np.ascontiguousarray(cv2.cvtColor(result.image, cv2.COLOR_RGB2BGR))
        label = f"{obj_id} {model.name.split('_')[0]}"
        cv2.putText(image, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, WHITE, 1, cv2.LINE_AA)
        panels.append(image)
    while len(panels) % FAMILY_COLUMNS:
        panels.append(np.zeros_like(panels[0]))
    rows = [
        np.hstack(panels[k : k + FAMILY_COLUMNS]) for k in range(0, len(panels), FAMILY_COLUMNS)
    ]
    return np.vstack(rows)


def write_family_sheet(catalog, out: str | Path, limit: int = 100) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), render_family_sheet(catalog, limit))
    return out
