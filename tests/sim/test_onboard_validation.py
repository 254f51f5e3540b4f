"""An onboarding's validation renders: rounds of held-out scenes until enough parts are scored,
and within a budget, rounds that stop where the renders and their evaluation would take more
than their share of what is left (never below the floor); the time the renders took is the
measure the training is sized from."""

import json
from pathlib import Path

import pytest

from posefuse.sim import onboard_validation as ov
from posefuse.sim.onboard import OnboardConfig


class FakeClock:
    """A clock that only the fake renderer advances."""

    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _fake_scenes(per_scene: list[int], clock: FakeClock | None = None, seconds: float = 0.0):
    """A stand-in for generate_dataset that writes scene k's scene_gt_info.json with
    ``per_scene[k]`` parts more than 75% visible in every view (and one barely visible), and
    advances ``clock`` by ``seconds`` a scene rendered."""
    calls = []

    def generate(catalog, root, config, show_progress=True, workers=1):
        calls.append((config.first_scene_id, config.n_scenes))
        for scene_id in range(config.first_scene_id, config.first_scene_id + config.n_scenes):
            folder = Path(root) / "test" / f"{scene_id:06d}"
            folder.mkdir(parents=True, exist_ok=True)
            parts = [{"visib_fract": 0.9}] * per_scene[scene_id] + [{"visib_fract": 0.2}]
            info = {str(im): parts for im in range(config.scene.n_views)}
            (folder / "scene_gt_info.json").write_text(json.dumps(info))
            if clock is not None:
                clock.now += seconds
        return Path(root)

    return generate, calls


def test_validation_renders_scenes_until_enough_parts_are_scored(tmp_path, monkeypatch):
    from posefuse.sim import synth

    generate, calls = _fake_scenes([3] * 10 + [30] * 30)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    config = OnboardConfig(held_instances=40)
    r = ov.render_validation(None, tmp_path / "v", "mixed", 7, config)
    # a first round from the guess (40 / 7.5: 6 scenes, 18 parts), then one sized from what the
    # scenes gave (3 a scene: 22 / 3, 8 more, of which the last four give 30)
    assert calls == [(0, 6), (6, 8)]
    assert r.scored["4"] == r.scored["8"] == 6 * 3 + 4 * 3 + 4 * 30 and r.scenes == 14
    assert r.views == 14 * 8 and r.seed == 7 and not r.fitted
    synth_json = json.loads((tmp_path / "v" / "synth.json").read_text())
    assert synth_json["n_scenes"] == r.scenes and synth_json["seed"] == 7
    # a part set whose scenes score nothing stops at the cap
    generate, calls = _fake_scenes([0] * 100)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    r = ov.render_validation(None, tmp_path / "w", "robi", 7, config)
    assert r.scenes == ov.MAX_HELD_SCENES and r.scored["8"] == 0
    # --held-scenes: exactly that many
    generate, calls = _fake_scenes([0] * 5)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    r = ov.render_validation(None, tmp_path / "x", "mixed", 7, OnboardConfig(held_scenes=2))
    assert r.scenes == 2 and calls == [(0, 2)]


def test_a_budgets_validation_probes_then_stops_where_its_time_runs_out(tmp_path, monkeypatch):
    from posefuse.sim import synth

    clock = FakeClock()
    generate, calls = _fake_scenes([5] * 40, clock, seconds=10.0)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    config = OnboardConfig(held_instances=100, held_views=8, workers=2)
    evaluation = 8 * ov.VALIDATION_S_PER_VIEW  # a scene's run, once rendered
    # room for 8 scenes and their evaluation, where 100 parts would need 20
    until = clock.now + 8 * (10.0 + evaluation) + 1.0
    r = ov.render_validation(None, tmp_path / "v", "mixed", 7, config, until, clock)
    # the probe: two scenes a render process; then what fits at the measured 10 s a scene
    assert calls[0] == (0, 4) and sum(n for _, n in calls) == 8, calls
    assert r.fitted and r.scored["8"] == 40 and r.render_s == 80.0
    assert clock.now + r.scenes * evaluation <= until
    # the floor: however short the time, at least MIN_HELD_INSTANCES parts
    clock = FakeClock()
    generate, calls = _fake_scenes([5] * 40, clock, seconds=10.0)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    r = ov.render_validation(None, tmp_path / "w", "mixed", 7, config, clock.now + 1.0, clock)
    assert r.fitted and r.scored["8"] == ov.MIN_HELD_INSTANCES and r.scenes == 6
    # enough room: the target, and nothing fitted
    clock = FakeClock()
    generate, calls = _fake_scenes([5] * 40, clock, seconds=10.0)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    r = ov.render_validation(None, tmp_path / "x", "mixed", 7, config, clock.now + 1e4, clock)
    assert not r.fitted and r.scored["8"] == 100 and r.scenes == 20


def test_both_profiles_share_the_budget_and_a_short_one_says_what_would_fit(tmp_path, monkeypatch):
    from posefuse.sim import synth

    clock = FakeClock()
    generate, _ = _fake_scenes([5] * 40, clock, seconds=10.0)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    config = OnboardConfig(held_instances=100, held_views=8, workers=2, minutes=15.0)
    notes = []
    deadline = clock.now + 600.0
    rendered = ov.render_validations(tmp_path, None, config, deadline, notes.append, clock)
    assert set(rendered) == {"mixed", "robi"}
    spent = clock.now - 1000.0
    pending = sum(r.views for r in rendered.values()) * ov.VALIDATION_S_PER_VIEW
    # the renders and the evaluation still to run within the share (the floor aside)
    assert spent + pending <= ov.VALIDATION_SHARE_MAX * 600.0
    assert rendered["mixed"].fitted and rendered["robi"].fitted
    short = [n for n in notes if "note:" in n]
    assert len(short) == 1 and "short of 100 a profile (--minutes" in short[0]
    # each round says how far the renders are
    assert any(n.startswith("  mixed: 4 scenes rendered, 20 parts scored") for n in notes), notes
    # a target the person chose is kept, whatever the budget
    clock = FakeClock()
    generate, _ = _fake_scenes([5] * 40, clock, seconds=10.0)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    chosen = OnboardConfig(held_instances=50, fit_validation=False)
    rendered = ov.render_validations(tmp_path / "c", None, chosen, deadline, notes.append, clock)
    assert all(r.scored["8"] == 50 and not r.fitted for r in rendered.values())
    # no budget (a fixed number of steps): the target
    rendered = ov.render_validations(tmp_path / "n", None, chosen, None, notes.append, clock)
    assert all(r.scored["8"] == 50 for r in rendered.values())
    assert sum("note:" in n for n in notes) == 1


def test_the_validation_is_timed_on_one_scene_of_each_profile(tmp_path, monkeypatch):
    """What the training keeps back for the validation: each profile's loading once and its
    first scene's work times its scenes, measured with the model it is given."""
    clock = FakeClock()
    asked = []

    def evaluate(root, model_path, config, scene_ids=None, setup=None):
        asked.append((Path(root).name, model_path, scene_ids))
        clock.now += 3.0  # loading the model and the templates
        setup()
        clock.now += 10.0 if Path(root).name == "mixed" else 25.0  # the scene's views
        return None

    monkeypatch.setattr(ov, "evaluate_profile", evaluate)

    def rendered(scenes):
        return ov.RenderedValidation(7, scenes, scenes * 8, {"8": 0}, 1.0, False)

    seconds = ov.validation_seconds(
        tmp_path,
        tmp_path / "init.onnx",
        OnboardConfig(),
        {"mixed": rendered(10), "robi": rendered(6)},
        clock,
    )
    assert asked == [
        ("mixed", tmp_path / "init.onnx", (0,)),
        ("robi", tmp_path / "init.onnx", (0,)),
    ]
    margin = ov.VALIDATION_MARGIN
    assert seconds == pytest.approx(3.0 + 10 * 10.0 * margin + 3.0 + 6 * 25.0 * margin)
    assert margin >= 1.0


def test_on_a_slow_cpu_the_evaluation_is_guessed_from_the_renders(tmp_path, monkeypatch):
    """Renders four times slower than the fake of above (40 s a scene, 5 s a view): the
    evaluation of a view is guessed at EVALUATION_PER_RENDER of its render's time (2 s, not
    0.7), and fewer scenes fit the same room."""
    from posefuse.sim import synth

    assert ov.evaluation_s_per_view(0.0, 0) == ov.VALIDATION_S_PER_VIEW
    assert ov.evaluation_s_per_view(80.0, 64) == ov.VALIDATION_S_PER_VIEW  # a fast CPU
    assert ov.evaluation_s_per_view(320.0, 64) == ov.EVALUATION_PER_RENDER * 5.0
    clock = FakeClock()
    generate, calls = _fake_scenes([5] * 40, clock, seconds=40.0)
    monkeypatch.setattr(synth, "generate_dataset", generate)
    config = OnboardConfig(held_instances=100, held_views=8, workers=2)
    evaluation = 8 * ov.EVALUATION_PER_RENDER * 5.0
    until = clock.now + 8 * (40.0 + evaluation) + 1.0  # room for 8 scenes and their evaluation
    r = ov.render_validation(None, tmp_path / "v", "mixed", 7, config, until, clock)
    assert r.fitted and r.scenes == 8, calls  # at 0.7 s a view, 9 would have been rendered
    assert clock.now + r.scenes * evaluation <= until
