"""`posefuse run-dataset` with the oracle: per-view-count translation errors on a BOP dataset."""

import csv

import pytest

from posefuse.cli.main import main


@pytest.fixture(scope="module")
def eight_view_root(tmp_path_factory, robi_catalog):
    """One scene of 6-8 parts seen from 8 views at 640x360."""
    from conftest import render_small_dataset

    root = tmp_path_factory.mktemp("bop8") / "eight"
    return render_small_dataset(root, robi_catalog, 1, 12, (6, 8), 8)


def test_run_dataset_writes_errors_at_2_4_and_8_views(eight_view_root, tmp_path, capsys):
    """Rows at 2, 4 and 8 views (never 1: a track is founded on two), and more views
    triangulate better: the median error shrinks from 2 to 8 views."""
    import numpy as np

    out = tmp_path / "run"
    code = main(
        [
            "run-dataset",
            "--dataset",
            str(eight_view_root),
            "--out",
            str(out),
            "--quiet",
            "--drop-rate",
            "0",
            "--false-positive-rate",
            "0",
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "| object | 2 views | 4 views | 8 views |" in text
    assert "Association: precision 1.0000, recall 1.0000" in text
    rows = list(csv.DictReader((out / "translation_errors.csv").open()))
    by_views = {}
    for r in rows:
        by_views.setdefault(int(r["n_views"]), []).append(float(r["rel_error"]))
    assert set(by_views) == {2, 4, 8}, sorted(by_views)
    median = {n: float(np.median(e)) for n, e in by_views.items()}
    assert median[2] < 0.02  # two views triangulate
    assert median[8] < median[2], median
    # the tracks' NEES by the views fused, as the rows give it
    nees = {n: [float(r["nees"]) for r in rows if int(r["n_views"]) == n] for n in (2, 4, 8)}
    shown = ", ".join(f"{n}: {np.mean(v):.2f} / {np.median(v):.2f}" for n, v in nees.items())
    assert "By the views fused, mean / median" in text and shown in text, shown
    assert len(by_views[8]) >= 4  # most parts of the bin are scored at 8 views
    # each row says how its track was published; the summary gives the confirmed ones apart
    assert {r["published"] for r in rows if int(r["n_views"]) > 1} <= {"confirmed", "tentative"}
    final = [
        float(r["nees"]) for r in rows if r["n_views"] == "8" and r["published"] == "confirmed"
    ]
    assert f"Of them the {len(final)} of {len(by_views[8])} published confirmed" in text


def test_run_dataset_refuses_bad_settings(small_dataset_root, tmp_path, capsys):
    args = ["run-dataset", "--dataset", str(small_dataset_root), "--out", str(tmp_path), "--quiet"]
    assert main([*args, "--drop-rate", "1.5"]) == 2
    assert "drop_rate must be in [0, 1]" in capsys.readouterr().err
    assert main([*args, "--scenes", "9"]) == 2
    assert "no scene 9" in capsys.readouterr().err
    assert main([*args, "--frontend", "magic"]) == 2
    assert "'magic' is not known" in capsys.readouterr().err


def test_both_steps_end_to_end_and_deterministic(small_dataset_root, default_banks):
    import numpy as np

    from posefuse.estimator.tracker import MultiViewEstimator
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.oracle import OracleConfig, OracleFrontend
    from posefuse.evaluation.run_dataset import run_dataset
    from posefuse.evaluation.scores import evaluate

    ds = load_dataset(small_dataset_root)

    def run():
        return run_dataset(
            ds,
            OracleFrontend(ds, OracleConfig(seed=3)),
            checkpoints=(1, 2),
            show_progress=False,
            rotation=True,
            estimator_factory=lambda: MultiViewEstimator(ds.catalog, banks=default_banks),
        )

    a, b = run(), run()
    assert a.results[1] == [] and len(a.results[2]) > 5  # a track needs two views
    assert evaluate(ds, a.results[2], targets=a.targets[2]).n_instances > 5
    for x, y in zip(a.results[2], b.results[2], strict=True):
        assert (x.scene_id, x.im_id, x.obj_id, x.score) == (y.scene_id, y.im_id, y.obj_id, y.score)
        np.testing.assert_array_equal(x.T_cam_obj, y.T_cam_obj)
    # every published pose of a confirmed track is measured against its covariance
    assert len(a.pose_nees[2]) > 5 and a.pose_nees[2] == b.pose_nees[2]
    assert np.all(np.isfinite(a.pose_nees[2])) and np.all(np.array(a.pose_nees[2]) >= 0)


def test_pose_nees_charges_the_error_under_the_covariance_and_not_the_symmetry():
    """An estimate that is the truth turned by a symmetry, then moved by (e_t, dphi), has the
    NEES of (e_t, dphi) under the covariance's blocks: the symmetry costs nothing."""
    import numpy as np

    from posefuse.estimator.core.geometry import so3_exp
    from posefuse.evaluation.tracking import pose_nees

    rng = np.random.default_rng(4)
    flip = so3_exp(np.array([0.0, 0.0, np.pi]))  # 180 degrees about z
    discrete = np.stack([np.eye(3), flip])
    T_true = np.eye(4)
    T_true[:3, :3] = so3_exp(rng.normal(size=3))
    T_true[:3, 3] = rng.normal(size=3)
    e_t, dphi = np.array([0.002, -0.001, 0.003]), np.deg2rad([1.0, -2.0, 0.5])
    T_est = np.eye(4)
    T_est[:3, :3] = so3_exp(-dphi) @ T_true[:3, :3] @ flip
    T_est[:3, 3] = T_true[:3, 3] - e_t
    A = rng.normal(size=(6, 6))
    cov = A @ A.T + 1e-4 * np.eye(6)
    n_t, n_R = pose_nees(T_est, cov, T_true, discrete, np.zeros((0, 3)))
    np.testing.assert_allclose(n_t, e_t @ np.linalg.solve(cov[:3, :3], e_t), rtol=1e-9)
    np.testing.assert_allclose(n_R, dphi @ np.linalg.solve(cov[3:, 3:], dphi), rtol=1e-6)
    # without the symmetry in the catalog, the flip is charged in full
    _, n_flip = pose_nees(T_est, cov, T_true, discrete[:1], np.zeros((0, 3)))
    assert n_flip > 100 * n_R


@pytest.fixture(scope="module")
def four_view_dataset(tmp_path_factory, robi_catalog):
    """3 bins x 4 views at 640x360 with 8-12 parts each."""
    from tests.conftest import render_small_dataset

    root = tmp_path_factory.mktemp("bop4") / "four"
    return render_small_dataset(root, robi_catalog, 3, 12, (8, 12), 4)


def test_random_rotations_fail_add_sym_and_the_oracle_run_passes_well_above(
    four_view_dataset, tmp_path, capsys, default_banks
):
    """ADD-sym does not forgive a wrong rotation (ADI does); the estimator is far above that."""
    import json

    import numpy as np
    from scipy.spatial.transform import Rotation

    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.scores import PoseResult, evaluate, ground_truth_results

    ds = load_dataset(four_view_dataset)
    rng = np.random.default_rng(7)
    guesses = []
    for r in ground_truth_results(ds):  # the true translation, a random rotation
        T = r.T_cam_obj.copy()
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        guesses.append(PoseResult(r.scene_id, r.im_id, r.obj_id, 1.0, T))
    random_rotation = evaluate(ds, guesses).total
    assert random_rotation.n_instances > 50
    assert random_rotation.rate() < 0.10, random_rotation
    assert random_rotation.rate("adi") > 0.15  # what the lenient metric forgave

    out = tmp_path / "run"
    assert (
        main(["run-dataset", "--dataset", str(four_view_dataset), "--out", str(out), "--quiet"])
        == 0
    )
    text = capsys.readouterr().out
    assert "ADD-sym-0.1d" in text and "AR_MSSD" in text
    # a 4-view dataset has no 8-view rows, in the accuracy table nor in the fates
    assert "| **all** | 4 |" in text and "| **all** | 8 |" not in text
    assert "| mixed | **all** | 4 |" in text
    at4 = json.loads((out / "detection_rate.json").read_text())["4"]["all"]
    assert at4["instances"] > 20
    assert at4["add_sym"] > random_rotation.rate() + 0.4, at4
    assert at4["precision"] >= 0.55, at4
    # the estimates above each confidence threshold: the first row keeps them all
    kept = (out / "confidence.md").read_text()
    assert "| confidence >= | 2 views" in kept and kept in text + "\n"
    first = next(line for line in kept.splitlines() if line.startswith("| 0 |"))
    assert f"{100 * at4['add_sym']:.1f}%, {100 * at4['precision']:.1f}%" in first
    # each scored instance counts the views that detected it: a correct one needs two, none
    # more than the views seen; the not-detected ones are tallied by that count in fates.md
    import csv

    rows = list(csv.DictReader((out / "fates.csv").open()))
    assert rows and all(0 <= int(r["detected_views"]) <= int(r["n_views"]) for r in rows)
    assert all(int(r["detected_views"]) >= 2 for r in rows if r["fate"] == "correct")
    assert any(int(r["detected_views"]) > 0 for r in rows)
    fates_md = (out / "fates.md").read_text()
    assert "| never detected | in one view | in two or more views |" in fates_md


def test_a_model_cards_verification_settings_apply_unless_the_command_line_names_them():
    from posefuse.cli.run import card_settings, tracker_config, verification_settings
    from posefuse.estimator.verification.verify import VerificationConfig

    card = {
        "mask_weight": 0.5,
        "max_fit": 1.0,
        "refinement.floor_translation_frac": 0.02,
        "refinement.floor_rotation_deg": 3.0,
    }
    given = verification_settings(
        ["max_fit=none", "max_views=3", "refinement.floor_rotation_deg=2"]
    )
    config = tracker_config(verification=given).with_card(card_settings(card, given))
    assert config.verification.mask_weight == 0.5  # the card's
    assert config.verification.max_fit is None and config.verification.max_views == 3  # told
    assert config.refinement.floor_translation_frac == 0.02  # the card's floor
    assert config.refinement.floor_rotation_deg == 2.0  # told
    assert tracker_config().with_card(card_settings(None, {})) == tracker_config()
    default = VerificationConfig()
    assert tracker_config().with_card(None).verification.max_fit == default.max_fit


def test_verification_settings_from_the_command_line_replace_only_what_they_name():
    from posefuse.cli.run import tracker_config, verification_settings
    from posefuse.estimator.core.errors import PosefuseError
    from posefuse.estimator.verification.verify import VerificationConfig

    settings = verification_settings(["mask_weight=2.5", "max_views=3"])
    assert settings == {"mask_weight": 2.5, "max_views": 3}
    assert isinstance(settings["max_views"], int)
    config = tracker_config(verification=settings)
    default = VerificationConfig()
    assert config.verification.mask_weight == 2.5 and config.verification.max_views == 3
    assert config.verification.crease_weight == default.crease_weight
    assert config.verification.enabled and config.refinement.enabled
    # the ablation still switches both off, whatever was set
    off = tracker_config(no_verify=True, verification=settings)
    assert not off.verification.enabled and not off.refinement.enabled
    assert verification_settings(None) == {}
    # an optional setting takes "none": the settled check off
    assert verification_settings(["settled_margin=none"]) == {"settled_margin": None}
    assert verification_settings(["settled_margin=0.1"]) == {"settled_margin": 0.1}
    assert tracker_config(verification={"settled_margin": None}).verification.settled_margin is None
    # a switch takes 0 or 1
    assert verification_settings(["reuse_refinement=0"]) == {"reuse_refinement": False}
    reuse = tracker_config(verification={"reuse_refinement": False}).verification
    assert reuse.reuse_refinement is False
    # the edge settings it holds, by a dotted key
    edges = verification_settings(["edges.max_points=600", "edges.truncate_px=8"])
    assert edges == {"edges.max_points": 600, "edges.truncate_px": 8.0}
    nested = tracker_config(verification={**edges, "max_views": 3}).verification
    assert nested.edges.max_points == 600 and nested.edges.truncate_px == 8.0
    assert nested.edges.roi_size == VerificationConfig().edges.roi_size and nested.max_views == 3
    # the occlusion table off: rays cast for every pose
    exact = tracker_config(verification=verification_settings(["edges.occlusion_directions=0"]))
    assert exact.verification.edges.occlusion_directions == 0
    # a value the edge settings refuse is a PosefuseError naming them
    # the refinement's settings, by a dotted key too
    refine = verification_settings(["refinement.sample_stride=3", "refinement.accept_frac=0.2"])
    assert refine == {"refinement.sample_stride": 3, "refinement.accept_frac": 0.2}
    both = tracker_config(verification={**refine, "sample_stride": 2})
    assert both.refinement.sample_stride == 3 and both.refinement.accept_frac == 0.2
    assert both.verification.sample_stride == 2 and both.refinement.enabled
    assert verification_settings(["refinement.accept_frac_max=none"]) == {
        "refinement.accept_frac_max": None
    }
    assert (
        tracker_config(verification={"refinement.accept_frac_max": None}).refinement.accept_frac_max
        is None
    )
    # the turn judge's settings, and its switch
    judge = verification_settings(["turns.effective_share=1", "turns.enabled=0"])
    assert judge == {"turns.effective_share": 1.0, "turns.enabled": False}
    judged = tracker_config(verification={**judge, "max_views": 4}).verification
    assert judged.turns.effective_share == 1.0 and not judged.turns.enabled
    assert judged.max_views == 4 and judged.enabled
    assert judged.turns.distinct_frac == VerificationConfig().turns.distinct_frac
    for bad, says in (
        ({"refinement.sample_stride": 0}, "refinement"),
        ({"sample_stride": 0}, "verification config"),
        ({"turns.effective_share": 0.0}, "turns"),
    ):
        with pytest.raises(PosefuseError, match=says):
            tracker_config(verification=bad)
    for bad in (
        {"edges.max_points": 0},
        {"edges.roi_size": 8},
        {"edges.occlusion_directions": -1},
        {"edges.occlusion_shell_ratio": 1.0},
    ):
        with pytest.raises(PosefuseError, match="edges"):
            tracker_config(verification=bad)
    for bad, says in [
        ("mask=1", "mask=1"),
        ("mask_weight", "KEY=VALUE"),
        ("mask_weight=heavy", "'heavy' is not a number"),
        ("edges=1", "edges=1"),
        ("edges.max_faces_x=1", "edges.max_faces_x"),
        ("reuse_refinement=maybe", "'maybe' is not 0 or 1"),
        ("enabled=0", "enabled=0"),
        ("mask_weight=none", "'none' is not a number"),  # only an optional setting is off
    ]:
        with pytest.raises(PosefuseError, match=says):
            verification_settings([bad])


def test_the_summary_gives_the_published_poses_nees_and_that_of_the_right_ones_apart():
    """translation_summary.md: the published poses' NEES, and then that of the right ones only
    (ADD-sym < 0.1 d), which a Gaussian can cover; a wrong basin is no Gaussian's to cover."""
    from types import SimpleNamespace

    from posefuse.evaluation.ambiguity import AmbiguityRow
    from posefuse.evaluation.run_dataset import DatasetRun, right_pose_coverage, summary_markdown
    from posefuse.evaluation.tracking import AssociationScore

    nees = [(1.0, 2.0), (3.0, 4.0), (100.0, 500.0), (5.0, 9.0)]
    right = [True, True, False, True]
    rows = [AmbiguityRow(8, 1, 0.0, False, r, r) for r in right]
    run = DatasetRun(
        rows=(),
        association=AssociationScore(1.0, 1.0, 4, 4),
        results={},
        targets={},
        pose_nees={8: nees},
        ambiguity={8: rows},
    )
    text = summary_markdown(run, {1: SimpleNamespace(name="part")}, checkpoints=(8,))
    assert "Published poses after 8 views (4): median NEES of the translation 4.00" in text
    assert "inside their 95% ellipsoid 75% and 50%." in text
    assert "Of them right (ADD-sym < 0.1 d, 3), what a Gaussian can cover:" in text
    assert "cover: median 3.00 and 4.00;" in text
    assert "inside 100% and 67%." in text
    coverage = right_pose_coverage(run, 8)  # what onboarding's validation keeps
    assert coverage["right_poses"] == 3 and coverage["inside_95_translation"] == 1.0
    assert abs(coverage["inside_95_rotation"] - 2 / 3) < 1e-12
    # without the rows of those poses (a run from before them) the line is left out
    run = DatasetRun((), AssociationScore(1.0, 1.0, 4, 4), {}, {}, pose_nees={8: nees})
    assert "Of them right" not in summary_markdown(run, {1: SimpleNamespace(name="p")}, (8,))
    assert right_pose_coverage(run, 8) is None and right_pose_coverage(run, 4) is None


def test_run_dataset_gives_the_estimator_the_bin_the_dataset_records(
    small_dataset_root, tmp_path, monkeypatch, capsys
):
    """As a cell that knows its bin: the one synth recorded (its own), unless ``--bin none``."""
    import posefuse.estimator.tracker as tracker
    from posefuse.evaluation.dataset import load_dataset

    made = []

    class Recording(tracker.MultiViewEstimator):
        def __init__(self, catalog, config=None, *args, **kwargs):
            made.append(config)
            super().__init__(catalog, config, *args, **kwargs)

    monkeypatch.setattr(tracker, "MultiViewEstimator", Recording)
    recorded = load_dataset(small_dataset_root).bin
    args = ["run-dataset", "--dataset", str(small_dataset_root), "--out", str(tmp_path)]
    for flag, used in (([], True), (["--bin", "none"], False)):
        made.clear()
        assert main([*args, "--translation-only", "--scenes", "0", *flag]) == 0
        bins = [None if c.bin is None else c.bin.to_json() for c in made]
        assert made and bins == [recorded.to_json() if used else None] * len(made)
        assert ("bin: from the dataset" in capsys.readouterr().out) == used
