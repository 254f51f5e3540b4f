"""One fate per scored instance: each rule of estimator/fates.py on a constructed view."""

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from posefuse.evaluation.fates import (
    FATES,
    TrackPose,
    fate_table,
    instance_fates,
    not_detected_table,
)

SCREW = 2  # continuous symmetry about z


@dataclass
class _Gt:
    obj_id: int
    T_cam_obj: np.ndarray
    visib_fract: float = 1.0


@dataclass
class _View:
    gts: list
    scene_id: int = 0
    im_id: int = 3


def _T(rotvec=(0, 0, 0), t=(0, 0, 0.7)):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_every_fate_in_order(robi_catalog):
    d = robi_catalog[SCREW].diameter
    gts = [_Gt(SCREW, _T(t=(0.2 * k - 0.8, 0, 0.7))) for k in range(11)]
    gts.append(_Gt(SCREW, _T(t=(1.0, 0, 0.7)), visib_fract=0.5))  # not scored
    gts.append(_Gt(SCREW, _T(t=(1.2, 0, 0.7))))
    truth = [g.T_cam_obj for g in gts]

    def moved(k, rotvec=(0, 0, 0), dt=(0, 0, 0)):
        T = truth[k] @ _T(rotvec, (0, 0, 0))
        T[:3, 3] += dt
        return T

    tracks = [
        # 0: right, up to its continuous symmetry (a turn about its own axis)
        TrackPose("a", SCREW, 0.9, moved(0, rotvec=(0, 0, 2.0))),
        # 1: seen once only (no track)
        # 2: split over two tracks, evenly
        TrackPose("b1", SCREW, 0.5, None),
        TrackPose("b2", SCREW, 0.5, None),
        # 3 and 4: one track holds both
        TrackPose("c", SCREW, 0.8, moved(3, dt=(0.1, 0, 0))),
        # 5: a track without a pose yet
        TrackPose("e", SCREW, 0.4, None),
        # 6: translation off by 0.3 d along the view
        TrackPose("f", SCREW, 0.7, moved(6, dt=(0, 0, 0.3 * d))),
        # 7: end over end
        TrackPose("g", SCREW, 0.7, moved(7, rotvec=(np.pi, 0, 0))),
        # 8: tilted by 40 degrees
        TrackPose("h", SCREW, 0.7, moved(8, rotvec=(np.deg2rad(40), 0, 0))),
        TrackPose("i", SCREW, 0.7, moved(9, rotvec=(np.deg2rad(40), 0, 0))),
        # 12: tilted too; one stray detection went to another live track (a wrong founding
        # pair), and its own track took one stray detection of another instance: its track's
        # fate all the same, neither split nor merged
        TrackPose("j", SCREW, 0.7, moved(12, rotvec=(np.deg2rad(40), 0, 0))),
    ]
    members = {
        "a": [0, 0, 0],
        "x": [1],
        "b1": [2, 2],
        "b2": [2, 2],
        "c": [3, 3, 4, 4],
        "e": [5, 5],
        "f": [6, 6, 6, 12],
        "g": [7, 7, 7],
        "h": [8, 8, -1],
        # 9: tilted as 8, one early detection held by a track dropped since ("old", not among
        # the tracks): still its live track's fate, not a split
        "i": [9, 9, 9],
        "old": [9, 10],
        # 10: its only other track dropped too: no track reports it
        "old2": [10],
        "j": [12, 12, 12, 5],
    }
    fates = instance_fates(_View(gts), robi_catalog, 4, tracks, members)
    got = {f.gt_idx: f.fate for f in fates}
    assert 11 not in got  # barely visible: not scored
    assert got == {
        0: "correct",
        1: "not detected",
        2: "split",
        3: "merged",
        4: "merged",
        5: "no pose",
        6: "translation off",
        7: "rotation flipped",
        8: "rotation off",
        9: "rotation off",
        10: "no pose",
        12: "rotation off",
    }
    table = fate_table(fates, robi_catalog, "robi")
    all_row = next(line for line in table.splitlines() if "**all**" in line)
    cells = [c.strip() for c in all_row.strip("|").split("|")]
    assert cells[:4] == ["robi", "**all**", "4", "12"]
    assert sum(int(c) for c in cells[4:]) == 12 and len(cells[4:]) == len(FATES)


def test_an_instance_not_detected_counts_the_views_that_detected_it(robi_catalog):
    """Not detected: fewer than two detections taken by tracks. How many views detected it at
    all (held detections too) tells the front end's miss from the founding's."""
    gts = [_Gt(SCREW, _T(t=(0.2 * k - 0.4, 0, 0.7))) for k in range(5)]
    tracks = [TrackPose("a", SCREW, 0.9, gts[3].T_cam_obj.copy())]
    members = {"a": [3, 3, 3], "x": [4]}  # 4: one detection taken by a dropped track
    # 0 never detected; 1 detected in one view (held); 2 in three views, none taken
    detected = {1: 1, 2: 3, 3: 3, 4: 2}
    fates = instance_fates(_View(gts), robi_catalog, 4, tracks, members, detected=detected)
    got = {f.gt_idx: (f.fate, f.detected_views) for f in fates}
    assert got == {
        0: ("not detected", 0),
        1: ("not detected", 1),
        2: ("not detected", 3),
        3: ("correct", 3),
        4: ("not detected", 2),
    }
    table = not_detected_table(fates, robi_catalog, "robi")
    all_row = next(line for line in table.splitlines() if "**all**" in line)
    cells = [c.strip() for c in all_row.strip("|").split("|")]
    assert cells == ["robi", "**all**", "4", "4", "1", "1", "2"]
    # without the counts every instance reads as never detected
    plain = instance_fates(_View(gts), robi_catalog, 4, tracks, members)
    assert {f.detected_views for f in plain} == {0}
