"""The contact sheet shows the edges that tell a near-symmetry's turns apart
(sim.contact_sheet): a square plate with a small block near one corner, kept 4-fold as a
near-symmetry, gets orange dots on its block and a line saying how many; the same part without
the near-symmetry gets neither."""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from posefuse.estimator.core.objects import make_model
from posefuse.estimator.core.symmetry import SymmetryAxis, SymmetryReport
from posefuse.sim.contact_sheet import ORANGE, PANEL, distinguishing_edges, render_contact_sheet


def _plate_with_block():
    plate = trimesh.creation.box((0.08, 0.08, 0.008))
    block = trimesh.creation.box((0.01, 0.01, 0.006))
    block.apply_translation([0.025, 0.025, 0.007])
    return trimesh.util.concatenate([plate, block])


def test_the_edges_that_tell_the_turns_apart_are_drawn_where_they_show():
    quarter = SymmetryAxis((0.0, 0.0, 1.0), 4, 0.01)
    plain = make_model(1, "plate", _plate_with_block(), detect=False)
    near = dataclasses.replace(plain, near_symmetries=(quarter,))
    report = SymmetryReport(np.zeros((0, 4, 4)), ())

    assert distinguishing_edges(plain) is None
    edges = distinguishing_edges(near)
    assert edges is not None
    block = np.abs(edges.points[:, :2] - [0.025, 0.025]).max(axis=1) <= 0.005 + 1e-6
    assert np.all(block)

    def orange_in_panels(image):
        panels = image[:, : 3 * PANEL]
        return int(np.all(panels == ORANGE, axis=2).sum())

    def orange_text(image):
        return int(np.all(image[:, 3 * PANEL :] == ORANGE, axis=2).sum())

    with_dots, without = render_contact_sheet(near, report), render_contact_sheet(plain, report)
    assert orange_in_panels(with_dots) > 20 and orange_in_panels(without) == 0
    assert orange_text(with_dots) > 0 and orange_text(without) == 0
