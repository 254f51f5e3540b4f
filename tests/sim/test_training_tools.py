"""The training tools: bench.frontend_seen scores a training set's views as eval-frontend scores
a dataset (one to one, same class, within 15 px, recall over the parts more than 75% visible),
and bench.training_curve continues a fine-tune's curve from its base's."""

import numpy as np

from posefuse.bench.frontend_seen import boxed_parts, found_parts, score_boxes, score_view
from posefuse.estimator.frontend.detection import Detection
from posefuse.estimator.frontend.two_stage import Box


def _row(cls, u, v, visib):
    # view, instance, class, u, v, x0, y0, x1, y1, visib_fract, visible_px
    return [0, 0, cls, u, v, u - 10, v - 10, u + 10, v + 10, visib, 400]


def _det(obj_id, u, v):
    return Detection(
        obj_id, np.array([u - 10, v - 10, 20, 20.0]), np.array([u, v]), np.eye(2), None, 0.9
    )


def test_one_to_one_same_class_within_15_px_recall_over_the_visible_parts():
    class_of = {1: 7, 2: 9}
    rows = np.array(
        [
            _row(1, 100, 100, 0.9),  # found by the first detection
            _row(1, 104, 100, 0.9),  # the same detection can't also find this one
            _row(2, 300, 300, 0.9),  # a detection of another class is near: not found
            _row(1, 500, 500, 0.5),  # barely visible, found: not in recall, matched for precision
            _row(1, 700, 700, 0.95),  # the detection is 16 px away: not found
        ],
        float,
    )
    dets = [_det(7, 101, 100), _det(7, 300, 302), _det(7, 500, 503), _det(7, 716, 700)]
    found, parts, matched = score_view(dets, rows, class_of)
    assert (found, parts, matched) == (1, 4, 2)
    # part by part (what --by-object counts per part type): the barely visible one is matched
    # for precision but is not a found part
    per_part, matched = found_parts(dets, rows, class_of)
    assert per_part.tolist() == [True, False, False, False, False] and matched == 2
    # the second part is found by a second detection beside the first
    found, parts, matched = score_view(dets + [_det(7, 104, 101)], rows, class_of)
    assert (found, parts, matched) == (2, 4, 3)
    assert score_view([], rows, class_of) == (0, 4, 0)


def test_stage_one_alone_is_scored_by_the_visible_boxes_centres_one_to_one():
    class_of = {1: 7, 2: 9}
    rows = np.array(
        [
            _row(1, 100, 100, 0.9),
            _row(1, 104, 100, 0.9),  # one box cannot find both
            _row(2, 300, 300, 0.9),  # a box of the other class is there
            _row(1, 500, 500, 0.5),  # barely visible: not counted
        ],
        float,
    )
    rows[0, 5:9] = [80, 90, 130, 110]  # its visible box is centred at (105, 100), not at (100, 100)

    def box(k, u, v):
        return Box(k, np.array([u, v], float), np.array([20.0, 20.0]), 0.9)

    boxes = [box(0, 105, 100), box(0, 300, 300), box(0, 500, 500)]
    assert score_boxes(boxes, rows, class_of, any_class=False) == 1
    assert boxed_parts(boxes, rows, class_of, any_class=False).tolist() == [
        True,
        False,
        False,
        False,
    ]
    # a generalist's boxes are "a part": the one on the part of the other class finds it
    assert score_boxes(boxes, rows, class_of, any_class=True) == 2
    assert score_boxes(boxes + [box(0, 104, 101)], rows, class_of, any_class=False) == 2
    assert score_boxes([], rows, class_of, any_class=False) == 0


def test_a_fine_tunes_learning_curve_continues_its_bases():
    from posefuse.bench.training_curve import curve_table, lineage_curve

    def point(step, cpu):
        return {"step": step, "cpu_hours": cpu, "wall_hours": cpu / 2, "tuning": {}}

    first = {"step": 100, "cpu_seconds": 3600.0, "wall_seconds": 1800.0, "curve": [point(50, 0.5)]}
    second = {**first, "curve": [point(40, 0.4)], "step": 60, "init_from": first}
    state = {"curve": [point(10, 0.1), point(20, 0.2)], "init_from": second}
    curve = lineage_curve(state)
    assert [p["run"] for p in curve] == [1, 2, 3, 3]
    # each run counts on from the end of the one before: its steps and hours, scored or not
    assert [p["step"] for p in curve] == [50, 140, 170, 180]
    assert np.allclose([p["cpu_hours"] for p in curve], [0.5, 1.4, 2.1, 2.2])
    assert np.allclose([p["wall_hours"] for p in curve], [0.25, 0.7, 1.05, 1.1])
    assert lineage_curve({"curve": [point(5, 0.1)]}) == [{**point(5, 0.1), "run": 1}]
    assert curve_table(curve).splitlines()[2].startswith("| 1 | 50 | 0.50 | 0.25 |")


def test_bfloat16_autocast_only_where_the_cpu_has_bfloat16_instructions():
    from posefuse.sim.train import native_bf16

    head = "processor\t: 0\nvendor_id\t: X\nflags\t\t: fpu sse2 avx2 fma"
    assert not native_bf16(head + "\n")  # AVX2 only: torch emulates bfloat16, slower
    assert native_bf16(head + " avx512f avx512_bf16\n")
    assert native_bf16(head + " amx_tile amx_bf16\n")
    assert not native_bf16(head + " avx512f avx512_vnni\n")  # AVX-512 without its bf16 part
    assert not native_bf16("processor\t: 0\n")  # no flags line (another platform's file)
    assert not native_bf16("flags_other : avx512_bf16\n")  # only the line named "flags" counts


def test_posefuse_train_chooses_the_precision_by_the_cpu_unless_told():
    import argparse

    import pytest

    from posefuse.cli import train as train_cli

    parser = argparse.ArgumentParser()
    train_cli.register(parser.add_subparsers())
    base = ["train", "--out", "m.onnx"]
    assert train_cli.bf16_choice(parser.parse_args(base)) is None  # the CPU decides
    assert train_cli.bf16_choice(parser.parse_args([*base, "--fp32"])) is False
    assert train_cli.bf16_choice(parser.parse_args([*base, "--bf16"])) is True
    with pytest.raises(SystemExit):
        parser.parse_args([*base, "--fp32", "--bf16"])
