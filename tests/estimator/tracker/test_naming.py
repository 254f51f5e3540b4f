"""Detections of "a part" (a generalist front end's, obj_id ANY_PART) named by the tracker: by
the catalog's one part, by a track they fall on, or by the parts' templates."""

import dataclasses

import numpy as np
import pytest

from posefuse.estimator.core.objects import Catalog
from posefuse.estimator.frontend.detection import ANY_PART
from posefuse.estimator.rotation.matching import RotationMatcher
from posefuse.estimator.rotation.naming import class_similarities, name_part
from posefuse.estimator.rotation.render import DirectionalLight, Lighting, Renderer
from posefuse.estimator.rotation.templates import TEMPLATE_LIGHTS_CAM, TEMPLATE_MATERIAL
from posefuse.estimator.tracker import Frame, MultiViewEstimator
from posefuse.sim.scenes import REALSENSE_1280x720 as CAM
from posefuse.sim.scenes import SceneSpec
from posefuse.sim.sequences import make_sequence


def _as_any_part(detections):
    return [dataclasses.replace(d, obj_id=ANY_PART) for d in detections]


def test_with_one_part_every_part_is_that_part_to_the_bit(robi_catalog):
    one = Catalog([robi_catalog.by_name("gear")])
    seq = make_sequence(one, 2024, SceneSpec(n_views=6))
    named, labelled = MultiViewEstimator(one), MultiViewEstimator(one)
    for view in seq.views:
        named.update(view.frame, _as_any_part(view.detections))
        labelled.update(view.frame, view.detections)
        assert named.last_report.assigned == labelled.last_report.assigned
    a, b = named.estimates(), labelled.estimates()
    assert len(a) >= 3 and [e.object_id for e in a] == [e.object_id for e in b]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.T_world_obj, y.T_world_obj)


def test_a_part_on_a_track_takes_its_class_and_one_nowhere_waits_without_an_image(robi_catalog):
    """Three views with their classes found the tracks; afterwards the detections say only "a
    part" and the frames carry no image: those a track's prediction gates take its class, each
    the class of the instance it shows; the others are skipped, saying why, and found
    nothing."""
    seq = make_sequence(robi_catalog, 2025, SceneSpec(n_views=6))
    est = MultiViewEstimator(robi_catalog)
    for view in seq.views[:3]:
        est.update(view.frame, view.detections)
    assert len(est.tracks) >= 3
    named = skipped = 0
    for view in seq.views[3:]:
        est.update(view.frame, _as_any_part(view.detections))
        for j, object_id in est.last_report.assigned:
            assert est.tracks[object_id].obj_id == view.detections[j].obj_id
            named += 1
        for _, why in est.last_report.skipped:
            assert why == "a part with no image to name it by"
            skipped += 1
        assert not est.last_report.started
    assert named >= 10 and skipped >= 1, (named, skipped)


def test_name_part_sums_the_views_and_refuses_nothing_to_name_by():
    name = name_part([{1: 0.2, 2: 0.3, 3: 0.1}, {1: 0.35, 2: 0.1, 3: 0.0}])
    assert name.obj_id == 1 and name.views == 2
    assert name.scores == ((1, 0.55), (2, 0.4), (3, 0.1)) and name.margin == pytest.approx(0.15)
    assert name_part([{4: 0.5, 2: 0.5}]).obj_id == 2  # a tie: the smaller obj_id
    with pytest.raises(ValueError, match="no view"):
        name_part([{}, {}])
    with pytest.raises(ValueError, match="different parts"):
        name_part([{1: 0.2}, {2: 0.3}])
    with pytest.raises(ValueError, match="in front"):
        class_similarities(np.zeros((8, 8, 3), np.uint8), CAM.K, np.zeros(3), None, {})


def test_a_matcher_that_cannot_score_a_bank_is_named_in_the_error(default_banks):
    """A custom matcher (``MultiViewEstimator(matchers=...)``) with only ``bank`` and
    ``measure`` cannot name "a part": one clear error naming its part, not an AttributeError."""

    class MeasureOnly:
        def __init__(self, bank):
            self.bank = bank

        def measure(self, image, K, t_cam_obj, mask):
            return []

    obj_id = sorted(default_banks)[0]
    image = np.zeros((CAM.height, CAM.width, 3), np.uint8)
    t = np.array([0.0, 0.0, 0.5])
    with pytest.raises(TypeError, match=f"obj_id {obj_id} \\(MeasureOnly\\) cannot name a part"):
        class_similarities(image, CAM.K, t, None, {obj_id: MeasureOnly(default_banks[obj_id])})
    matcher = RotationMatcher(default_banks[obj_id])
    assert set(class_similarities(image, CAM.K, t, None, {obj_id: matcher})) == {obj_id}


def _render(models, poses):
    """An image of ``models`` at ``poses`` (T_cam_obj), lit as the templates are, on grey."""
    T_world_cam = np.eye(4)
    lights = tuple((tuple(np.asarray(d, float)), c) for d, c in TEMPLATE_LIGHTS_CAM)
    lighting = Lighting(
        tuple(DirectionalLight(d, c) for d, c in lights),
        ambient=(0.15, 0.15, 0.15),
        background=(0.3, 0.3, 0.3),
    )
    renderer = Renderer(
        [m.mesh for m in models], materials=[TEMPLATE_MATERIAL] * len(models), poses=poses
    )
    result = renderer.render(CAM, T_world_cam, lighting, shadows=False)
    return result.image, result.instance


def test_the_templates_name_a_part_at_its_true_translation(robi_catalog, default_banks):
    """Each catalog part rendered alone in three orientations, its visible box as its mask,
    scored at its true translation: its own class's templates stand out most in most of them,
    13 of 15 when written (chance is one in five)."""
    from scipy.spatial.transform import Rotation

    matchers = {k: RotationMatcher(default_banks[k]) for k in robi_catalog}
    right = total = 0
    for k, model in sorted(robi_catalog.items()):
        for seed in range(3):
            T = np.eye(4)
            T[:3, :3] = Rotation.random(random_state=100 * k + seed).as_matrix()
            T[:3, 3] = [0.03, -0.02, 0.55]
            image, instance = _render([model], [T])
            ys, xs = np.nonzero(instance >= 0)
            box = np.zeros(instance.shape, bool)
            box[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1] = True
            similar = class_similarities(image, CAM.K, T[:3, 3], box, matchers)
            assert sorted(similar) == sorted(robi_catalog)
            assert all(0.0 <= v <= 1.0 for v in similar.values())
            right += name_part([similar]).obj_id == k
            total += 1
    assert right >= 0.8 * total, f"{right} of {total} named right"


def test_a_generalists_parts_are_founded_and_named_from_two_views(robi_catalog, default_banks):
    """Two parts of different classes seen from two cameras, their detections only "a part":
    one track each, founded from the two views, named the part it is."""
    from posefuse.estimator.frontend.detection import Detection

    gear, tube = robi_catalog.by_name("gear"), robi_catalog.by_name("tube_fitting")
    world = {gear.obj_id: np.array([-0.06, 0.0, 0.0]), tube.obj_id: np.array([0.06, 0.02, 0.0])}
    est = MultiViewEstimator(robi_catalog, banks=default_banks)
    for stamp, x in enumerate((-0.08, 0.08)):
        T_world_cam = np.eye(4)
        T_world_cam[:3, 3] = [x, 0.0, -0.6]
        T_cam_world = np.linalg.inv(T_world_cam)
        poses, models, dets = [], [], []
        for obj_id, t in world.items():
            T = np.eye(4)
            T[:3, 3] = T_cam_world[:3, :3] @ t + T_cam_world[:3, 3]
            poses.append(T)
            models.append(robi_catalog[obj_id])
        image, instance = _render(models, poses)
        for k, T in enumerate(poses):
            ys, xs = np.nonzero(instance == k)
            uv = CAM.K[:2, :2] @ (T[:2, 3] / T[2, 3]) + CAM.K[:2, 2]
            box = [xs.min(), ys.min(), np.ptp(xs) + 1, np.ptp(ys) + 1]
            dets.append(Detection(ANY_PART, np.array(box, float), uv, np.eye(2), instance == k))
        est.update(Frame(stamp + 1, CAM, T_world_cam, image), dets)
    tracks = list(est.tracks.values())
    assert len(tracks) == 2, [t.object_id for t in tracks]
    for track in tracks:
        nearest = min(world, key=lambda k: np.linalg.norm(world[k] - track.estimate.t_world_obj))
        assert track.obj_id == nearest


def test_a_part_on_a_track_is_no_part_expected_and_a_class_reset_forgets_parts_held(
    robi_catalog,
):
    """A track's part found as "a part" covers it: no crop is asked there. "A part" held
    waiting for a partner may be of any class, so resetting one class forgets it too; the
    state with it held exports and imports."""
    seq = make_sequence(robi_catalog, 2026, SceneSpec(n_views=5))
    est = MultiViewEstimator(robi_catalog)
    for view in seq.views[:4]:
        est.update(view.frame, view.detections)
    last = seq.views[4]
    cam, T = last.frame.camera, last.frame.T_world_cam
    expected = est.expected_parts(cam, T, [])
    assert len(expected) >= 3
    as_parts = _as_any_part(last.detections)
    still = {e.object_id for e in est.expected_parts(cam, T, as_parts)}
    labelled = {e.object_id for e in est.expected_parts(cam, T, last.detections)}
    assert len(still) < len(expected) and still <= labelled, (still, labelled)
    # a part no track explains, in a frame with an image: held as "a part"
    far = dataclasses.replace(as_parts[0], center_uv=np.array([30.0, 30.0]))
    image = np.zeros((cam.height, cam.width, 3), np.uint8)
    est.update(Frame(last.frame.stamp_ns, cam, T, image), [far])
    assert [h.obj_id for h in est.held()].count(ANY_PART) == 1
    state = est.export_state()
    other = MultiViewEstimator(robi_catalog)
    other.import_state(state)
    assert [h.obj_id for h in other.held()].count(ANY_PART) == 1
    other.reset(class_id=sorted(robi_catalog)[0])
    assert ANY_PART not in [h.obj_id for h in other.held()]


def _held(obj_id, stamp, T_world_cam, point, K, box_depth):
    """A held detection of ``point`` (3,) world, seen by a camera at T_world_cam (4, 4)."""
    from posefuse.estimator.core.geometry import invert
    from posefuse.estimator.translation.founding import HeldDetection

    T_cam_world = invert(T_world_cam)
    p = T_cam_world[:3, :3] @ point + T_cam_world[:3, 3]
    uv = (K @ (p / p[2]))[:2]
    return HeldDetection(obj_id, stamp, 0, T_cam_world, K, uv, np.eye(2), box_depth, 0)


def test_a_part_absorbed_by_a_named_track_takes_its_parts_box_depth(robi_catalog):
    """A held "a part" that joins a track founded in the same view gets the box depth of the
    track's part (its generic depth times the part's size over the typical part's); a labelled
    detection, or a class the scale does not name, keeps its own."""
    from posefuse.estimator.tracker.config import TrackerConfig
    from posefuse.estimator.tracker.tracks import TrackBook
    from posefuse.estimator.translation.founding import FoundingConfig, triangulate_pair
    from posefuse.sim.scenes import look_at

    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    point = np.array([0.01, -0.02, 0.0])
    cams = [
        look_at(np.array([x, -0.5, 0.6]), np.zeros(3), np.array([0, 0, 1.0]))
        for x in (-0.3, 0.0, 0.3, 0.15)
    ]
    obj_id = sorted(robi_catalog)[0]
    book = TrackBook(robi_catalog, TrackerConfig())
    pair = triangulate_pair(
        _held(obj_id, 1, cams[0], point, K, 0.8),
        _held(obj_id, 2, cams[1], point, K, 0.8),
        FoundingConfig(),
    )
    assert pair is not None
    track = book.found_track(pair)
    unnamed = _held(ANY_PART, 3, cams[2], point, K, 0.5)
    labelled = _held(obj_id, 4, cams[3], point, K, 0.6)
    left = book.absorb_held([unnamed, labelled], [track], {obj_id: 1.6})
    assert left == []
    assert [r.box_depth for r in track.refs[-2:]] == pytest.approx([0.5 * 1.6, 0.6])
    other = TrackBook(robi_catalog, TrackerConfig())
    again = other.found_track(pair)
    other.absorb_held([unnamed], [again], {obj_id + 100: 1.6})
    assert again.refs[-1].box_depth == pytest.approx(0.5)
