"""Training is a resumable job: a run stopped and resumed ends where an uninterrupted one ends
(same batches, same schedule), keeps its cumulative CPU time, and fine-tuning for another
catalog keeps everything but the class heatmaps."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from posefuse.service.resources import DEFAULT_CATALOG  # noqa: E402
from posefuse.sim.train import TrainConfig, train  # noqa: E402


def _config(tmp_path, **kw) -> TrainConfig:
    base = dict(
        n_scenes=1,
        views_per_scene=1,
        val_scenes=1,
        minutes=1e6,  # never the limit: steps are
        max_iterations=6,
        warmup=2,
        batch=2,
        crop_batch=4,
        workers=1,
        data_dir=str(tmp_path / "data"),
        threads=1,
    )
    base.update(kw)
    return TrainConfig(**base)


def _weights(ckpt) -> dict:
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    return {
        **{f"det.{k}": v for k, v in state["nets"]["det"].items()},
        **{f"crop.{k}": v for k, v in state["nets"]["crop"].items()},
    }, state


def test_a_resumed_run_ends_where_an_uninterrupted_one_ends(tmp_path):
    straight = tmp_path / "straight"
    train(DEFAULT_CATALOG, straight / "m.onnx", _config(tmp_path))
    split = tmp_path / "split"
    train(DEFAULT_CATALOG, split / "m.onnx", _config(tmp_path, run_steps=3))
    w_half, half = _weights(split / "m.ckpt")
    assert half["step"] == 3 and half["cpu_seconds"] > 0
    # a resume keeps the checkpoint's schedule and stream, whatever this run is told
    card = train(
        DEFAULT_CATALOG,
        split / "m.onnx",
        _config(tmp_path, resume=str(split / "m.ckpt"), max_iterations=1000, seed=5),
    )
    w_split, end = _weights(split / "m.ckpt")
    w_straight, _ = _weights(straight / "m.ckpt")
    assert end["step"] == 6 and card["training"]["steps"] == 6
    assert end["cpu_seconds"] > half["cpu_seconds"]
    moved = 0
    for k, v in w_straight.items():
        if not v.is_floating_point():
            continue
        # the same batches, schedule and optimizer state: the same weights
        assert torch.allclose(w_split[k], v, rtol=1e-5, atol=1e-7), k
        moved += int(not torch.equal(w_half[k], v))
    assert moved > 10  # the second half did train
    assert (split / "m_crop.onnx").is_file()
    assert json.loads((split / "m.json").read_text())["kind"] == "two_stage"


def test_fine_tuning_replaces_only_the_class_heatmaps(tmp_path):
    from posefuse.sim.train import _Nets

    base = _Nets(5, _config(tmp_path))
    other = _Nets(2, _config(tmp_path, seed=1))
    fresh = other.init_from({"det": base.det.state_dict(), "crop": base.crop.state_dict()})
    assert fresh == ["heatmap.weight", "heatmap.bias"]
    for k, v in base.det.state_dict().items():
        if not k.startswith("heatmap."):
            assert torch.equal(other.det.state_dict()[k], v), k
    assert other.det.heatmap.weight.shape[0] == 2
    assert np.isclose(float(other.det.heatmap.bias[0]), -2.19)


def test_stage_two_widened_for_the_box_channel_starts_as_the_one_it_comes_from(tmp_path):
    from posefuse.sim.train import _Nets

    base = _Nets(5, _config(tmp_path, bf16=False))
    wide = _Nets(5, _config(tmp_path, bf16=False, crop_box_channel=True, seed=1))
    fresh = wide.init_from({"det": base.det.state_dict(), "crop": base.crop.state_dict()})
    assert fresh == ["crop.backbone.enc1.0.0.weight (box channel)"]
    base.crop.eval(), wide.crop.eval()
    x = torch.randn(2, 3, 96, 96, generator=torch.Generator().manual_seed(0))
    box = (torch.rand(2, 1, 96, 96) > 0.5).float()
    with torch.no_grad():
        assert torch.allclose(base.crop(x), wide.crop(torch.cat([x, box], 1)), atol=1e-5)
        # and it can learn to use the box: the new input has its own weights
        wide.crop.backbone.enc1[0][0].weight[:, 3] += 0.1
        assert not torch.allclose(base.crop(x), wide.crop(torch.cat([x, box], 1)), atol=1e-3)


def test_a_widened_stage_two_starts_as_the_narrow_one_and_its_copies_can_part(tmp_path):
    from posefuse.sim.net import CropVotingNet, widen_state
    from posefuse.sim.train import _Nets

    torch.manual_seed(3)
    narrow = CropVotingNet(8)
    narrow.train()
    with torch.no_grad():  # batch-norm statistics that are not the defaults
        for _ in range(3):
            narrow(torch.randn(4, 3, 32, 32))
    narrow.eval()
    wide = CropVotingNet(16)
    state, fresh = widen_state(narrow.state_dict(), wide.state_dict(), noise=0.0)
    assert fresh == []
    wide.load_state_dict(state)
    wide.eval()
    x = torch.randn(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert torch.allclose(narrow(x), wide(x), atol=1e-5)
    w = state["backbone.enc2.0.0.weight"]  # (32, 16, 3, 3) from (16, 8, 3, 3)
    assert w.shape == (32, 16, 3, 3)
    assert torch.equal(w[:16, :8], w[16:, 8:])  # copies of a channel, exactly
    # the noise parts the copies, seeded, and moves the output little
    noisy, _ = widen_state(narrow.state_dict(), wide.state_dict(), noise=0.01, seed=1)
    again, _ = widen_state(narrow.state_dict(), wide.state_dict(), noise=0.01, seed=1)
    w = noisy["backbone.enc2.0.0.weight"]
    assert not torch.equal(w[:16, :8], w[16:, 8:])
    assert all(torch.equal(noisy[k], again[k]) for k in noisy)
    wide.load_state_dict(noisy)
    wide.eval()
    with torch.no_grad():
        diff = (narrow(x) - wide(x)).abs().max()
    assert 0 < float(diff) < 0.1
    # a width that is not a multiple is left as the new network had it, and said
    odd = CropVotingNet(12)
    _, fresh = widen_state(narrow.state_dict(), odd.state_dict())
    assert "backbone.enc2.0.0.weight" in fresh
    # through fine-tuning: --crop-width 16 from a width-8 checkpoint
    base = _Nets(5, _config(tmp_path, bf16=False, width=8))
    wider = _Nets(5, _config(tmp_path, bf16=False, width=8, crop_width=16, seed=1))
    said = wider.init_from({"det": base.det.state_dict(), "crop": base.crop.state_dict()})
    assert said == ["stage two widened to width 16 (62 tensors)"]
    base.crop.eval(), wider.crop.eval()
    with torch.no_grad():
        assert torch.allclose(base.crop(x), wider.crop(x), atol=0.1)
        assert wider.crop(x).shape == base.crop(x).shape


def test_a_fine_tune_widens_stage_two_and_the_checkpoint_remembers_it(tmp_path):
    out = tmp_path / "base" / "m.onnx"
    train(DEFAULT_CATALOG, out, _config(tmp_path, width=8, max_iterations=2))
    wide = tmp_path / "wide" / "m.onnx"
    card = train(
        DEFAULT_CATALOG,
        wide,
        _config(tmp_path, init=str(tmp_path / "base" / "m.ckpt"), crop_width=16, max_iterations=2),
    )
    assert "CropVotingNet(width=16" in card["architecture"]
    assert "BoxDetectorNet(width=8)" in card["architecture"]
    w, state = _weights(tmp_path / "wide" / "m.ckpt")
    assert state["config"]["width"] == 8 and state["config"]["crop_width"] == 16
    assert w["crop.backbone.enc1.0.0.weight"].shape[0] == 16
    # a resume keeps the widths whatever it is told
    train(
        DEFAULT_CATALOG,
        wide,
        _config(tmp_path, resume=str(tmp_path / "wide" / "m.ckpt"), extend=(1, 1e-3)),
    )
    w, state = _weights(tmp_path / "wide" / "m.ckpt")
    assert state["config"]["crop_width"] == 16 and state["step"] == 3
    with pytest.raises(ValueError, match="crop-width 12"):
        train(
            DEFAULT_CATALOG,
            tmp_path / "odd" / "m.onnx",
            _config(tmp_path, init=str(tmp_path / "base" / "m.ckpt"), crop_width=12),
        )


def test_a_warm_restart_repeats_the_schedule_from_its_own_peak():
    config = TrainConfig(max_iterations=100, warmup=10, lr=2e-3).extended(50, 1e-3)
    assert config.total_steps == 150 and config.restarts == ((100, 150, 1e-3),)
    assert config.schedule(99) == pytest.approx(2e-3 * 0.02, rel=0.05)  # the first cosine ends
    assert config.schedule(100) == pytest.approx(1e-3 / 10)  # warm-up again, to the new peak
    assert config.schedule(109) == pytest.approx(1e-3)
    assert config.schedule(149) == pytest.approx(1e-3 * 0.02, rel=0.1)
    assert config.extended(10, 5e-4).restarts[-1] == (150, 160, 5e-4)
    with pytest.raises(ValueError, match="extend"):
        config.extended(0, 1e-3)


def test_a_schedule_by_the_clock_warms_up_then_anneals_to_the_deadline():
    from posefuse.sim.train import CLOCK_WARMUP

    config = TrainConfig(lr=2e-3, clock_schedule=True)
    assert config.clock_schedule_at(0.0) == pytest.approx(2e-5)  # never zero
    assert config.clock_schedule_at(CLOCK_WARMUP / 2) == pytest.approx(1e-3)
    assert config.clock_schedule_at(CLOCK_WARMUP) == pytest.approx(2e-3)
    assert config.clock_schedule_at(1.0) == pytest.approx(2e-3 * 0.02)
    assert config.clock_schedule_at(7.0) == pytest.approx(2e-3 * 0.02)  # past the deadline
    after = [config.clock_schedule_at(f) for f in np.linspace(CLOCK_WARMUP, 1.0, 50)]
    assert all(a >= b for a, b in zip(after, after[1:], strict=False))
    # halfway through the cosine, half the way down
    mid = CLOCK_WARMUP + (1 - CLOCK_WARMUP) / 2
    assert config.clock_schedule_at(mid) == pytest.approx(2e-3 * (0.02 + 0.49))


def test_extend_lengthens_a_finished_schedule_and_the_checkpoint_keeps_it(tmp_path):
    out = tmp_path / "m.onnx"
    train(DEFAULT_CATALOG, out, _config(tmp_path))
    w_end, end = _weights(tmp_path / "m.ckpt")
    card = train(
        DEFAULT_CATALOG,
        out,
        _config(tmp_path, resume=str(tmp_path / "m.ckpt"), extend=(3, 1e-3)),
    )
    w_more, more = _weights(tmp_path / "m.ckpt")
    assert end["step"] == 6 and more["step"] == 9
    assert [tuple(r) for r in more["config"]["restarts"]] == [(6, 9, 1e-3)]
    assert card["training"]["schedule_steps"] == 9
    assert any(not torch.equal(w_more[k], v) for k, v in w_end.items() if v.is_floating_point())
    # resuming the extended checkpoint without --extend has nothing left to do
    train(DEFAULT_CATALOG, out, _config(tmp_path, resume=str(tmp_path / "m.ckpt")))
    assert _weights(tmp_path / "m.ckpt")[1]["step"] == 9


def test_a_fine_tune_keeps_its_base_and_its_augmentation_through_a_resume(tmp_path):
    base_ckpt = tmp_path / "base" / "m.ckpt"
    train(DEFAULT_CATALOG, base_ckpt.with_suffix(".onnx"), _config(tmp_path))
    _, base = _weights(base_ckpt)
    assert base["config"]["dihedral"] is False and base["init_from"] is None
    tuned = tmp_path / "tuned" / "m.onnx"
    train(
        DEFAULT_CATALOG,
        tuned,
        _config(
            tmp_path,
            init=str(base_ckpt),
            dihedral=True,
            photometric=True,
            backgrounds=0.5,
            run_steps=3,
        ),
    )
    _, half = _weights(tuned.with_suffix(".ckpt"))
    assert half["config"]["dihedral"] is True and half["config"]["photometric"] is True
    assert half["config"]["backgrounds"] == 0.5
    # the base's step and CPU time are kept beside the fine-tune's own, which start at zero
    assert half["init_from"]["step"] == 6
    assert half["init_from"]["cpu_seconds"] == pytest.approx(base["cpu_seconds"])
    assert half["step"] == 3
    # a resume keeps both, whatever it is told
    card = train(
        DEFAULT_CATALOG,
        tuned,
        _config(tmp_path, resume=str(tuned.with_suffix(".ckpt")), dihedral=False),
    )
    assert "flips" in card["training"]["augmentation"]
    assert "photometric" in card["training"]["augmentation"]
    assert "clutter behind the parts in 50% of samples" in card["training"]["augmentation"]
    _, end = _weights(tuned.with_suffix(".ckpt"))
    # the card names where the weights came from, and counts the base's hours too
    assert card["training"]["initialised_from"] == str(base_ckpt)
    assert card["training"]["cumulative_cpu_hours"] == pytest.approx(
        (end["cpu_seconds"] + base["cpu_seconds"]) / 3600, abs=2e-3
    )
    assert end["step"] == 6 and end["config"]["dihedral"] is True
    assert end["config"]["photometric"] is True and end["config"]["backgrounds"] == 0.5
    assert end["init_from"]["step"] == 6
    # a checkpoint written before the option existed was trained without it, and resumes so
    state = torch.load(base_ckpt, map_location="cpu", weights_only=False)
    del state["config"]["dihedral"], state["config"]["photometric"]
    state["config"].pop("backgrounds")
    old = tmp_path / "old" / "m.ckpt"
    old.parent.mkdir()
    torch.save(state, old)
    train(
        DEFAULT_CATALOG,
        old.with_suffix(".onnx"),
        _config(
            tmp_path,
            resume=str(old),
            dihedral=True,
            photometric=True,
            backgrounds=1.0,
            extend=(2, 1e-3),
        ),
    )
    assert _weights(old)[1]["config"]["dihedral"] is False
    assert _weights(old)[1]["config"]["photometric"] is False
    assert _weights(old)[1]["config"]["backgrounds"] == 0.0


def test_the_proxy_voting_loss_finds_the_center_and_weighs_a_vote_by_its_distance():
    """The target vectors meet at the center they were drawn to; the loss is zero on them,
    and a vote turned by an angle costs its distance to the center times that angle."""
    from posefuse.sim.train import proxy_voting_loss, target_centers
    from posefuse.sim.train_targets import crop_targets

    S = 96
    inst = np.zeros((200, 200), np.uint8)
    inst[60:140, 70:150] = 1
    uv = np.array([101.3, 97.8])
    a, b = 1.4, np.array([30.0, 25.0])
    label, vec = crop_targets(inst, 0, uv, a, b, S)
    L, V = torch.from_numpy(label)[None, None], torch.from_numpy(vec)[None]
    center = target_centers(L, V)[0].numpy()
    expected = ((uv - b) / a - 1.5) / 4  # cell j is crop pixel 4 j + 1.5
    assert np.allclose(center, expected, atol=1e-3)
    assert float(proxy_voting_loss(V, L, V)) < 1e-6
    angle = 0.02
    c, s = np.cos(angle), np.sin(angle)
    turned = torch.stack([c * V[:, 0] - s * V[:, 1], s * V[:, 0] + c * V[:, 1]], 1)
    ys, xs = np.nonzero(label)
    dist = np.hypot(expected[0] - xs, expected[1] - ys) * np.sin(angle)
    expect = np.where(dist < 1, 0.5 * dist**2, dist - 0.5).mean()
    assert float(proxy_voting_loss(turned * 3.0, L, V)) == pytest.approx(expect, rel=1e-3)
    # a crop without a part adds nothing and stays finite
    empty = proxy_voting_loss(turned, torch.zeros_like(L), torch.zeros_like(V))
    assert float(empty) == 0.0


def test_a_resume_keeps_the_vote_loss_unless_told_and_logs_it_either_way(tmp_path):
    """The proxy voting loss's weight is kept in the checkpoint: a resume that does not name
    it goes on with it, one that does replaces it; the loss is logged with it off too."""
    out = tmp_path / "v" / "m.onnx"
    train(DEFAULT_CATALOG, out, _config(tmp_path, run_steps=3, vote_loss=0.5))
    state = torch.load(out.with_suffix(".ckpt"), map_location="cpu", weights_only=False)
    assert state["config"]["vote_loss"] == 0.5
    assert state["curve"][-1]["loss"]["vote"] > 0
    card = train(DEFAULT_CATALOG, out, _config(tmp_path, resume=str(out.with_suffix(".ckpt"))))
    assert card["training"]["proxy_voting_loss_weight"] == 0.5
    state = torch.load(out.with_suffix(".ckpt"), map_location="cpu", weights_only=False)
    assert state["step"] == 6 and state["config"]["vote_loss"] == 0.5
    off = tmp_path / "off" / "m.onnx"
    card = train(DEFAULT_CATALOG, off, _config(tmp_path, run_steps=3))
    assert card["training"]["proxy_voting_loss_weight"] == 0.0
    state = torch.load(off.with_suffix(".ckpt"), map_location="cpu", weights_only=False)
    assert state["config"]["vote_loss"] == 0.0 and state["curve"][-1]["loss"]["vote"] > 0


def test_another_input_scale_is_the_cards_and_the_front_end_runs_at_it(tmp_path):
    from posefuse.estimator.core.objects import load_catalog
    from posefuse.estimator.frontend.network import NetworkFrontend

    out = tmp_path / "s" / "m.onnx"
    card = train(DEFAULT_CATALOG, out, _config(tmp_path, input_scale=0.625, max_iterations=2))
    assert card["input_scale"] == 0.625
    _, state = _weights(out.with_suffix(".ckpt"))
    assert state["config"]["input_scale"] == 0.625
    frontend = NetworkFrontend(out, load_catalog(DEFAULT_CATALOG))
    heat = frontend.infer(np.zeros((720, 1280, 3), np.uint8))
    assert heat.shape[-2:] == (464 // 4, 800 // 4)
    # a resume keeps the checkpoint's scale, whatever it is told
    train(
        DEFAULT_CATALOG,
        out,
        _config(tmp_path, resume=str(out.with_suffix(".ckpt")), extend=(1, 1e-3)),
    )
    assert _weights(out.with_suffix(".ckpt"))[1]["config"]["input_scale"] == 0.625
    # a fine-tune keeps it unless told another: the same convolutions then learn at that one
    kept = tmp_path / "kept" / "m.onnx"
    train(DEFAULT_CATALOG, kept, _config(tmp_path, init=str(out.with_suffix(".ckpt")), seed=1))
    assert _weights(kept.with_suffix(".ckpt"))[1]["config"]["input_scale"] == 0.625
    told = tmp_path / "told" / "m.onnx"
    card = train(
        DEFAULT_CATALOG,
        told,
        _config(tmp_path, init=str(out.with_suffix(".ckpt")), input_scale=0.5, seed=1),
    )
    assert card["input_scale"] == 0.5
    assert NetworkFrontend(told, load_catalog(DEFAULT_CATALOG)).infer(
        np.zeros((720, 1280, 3), np.uint8)
    ).shape[-2:] == (368 // 4, 640 // 4)


def test_frozen_backbones_keep_their_weights_and_statistics_while_the_heads_learn(tmp_path):
    first = tmp_path / "first"
    train(DEFAULT_CATALOG, first / "m.onnx", _config(tmp_path))
    w_init, _ = _weights(first / "m.ckpt")
    tuned = tmp_path / "tuned"
    card = train(
        DEFAULT_CATALOG,
        tuned / "m.onnx",
        _config(tmp_path, init=str(first / "m.ckpt"), frozen_backbones=True, seed=1),
    )
    w_tuned, state = _weights(tuned / "m.ckpt")
    assert state["config"]["frozen_backbones"] is True
    assert card["training"]["frozen_backbones"] is True
    backbone = [k for k in w_init if ".backbone." in f".{k}"]
    assert backbone, sorted(w_init)[:5]
    for k in backbone:  # weights and batch-norm statistics alike
        assert torch.equal(w_tuned[k], w_init[k]), k
    heads = [k for k in w_init if ".backbone." not in f".{k}" and w_init[k].is_floating_point()]
    assert sum(not torch.equal(w_tuned[k], w_init[k]) for k in heads) > 4


def test_a_budgeted_run_keeps_back_what_follows_its_loop(tmp_path, capsys):
    """With a deadline (onboarding's budget) the loop ends early by the export, the calibration
    passes and the caller's own work after it, measured before the loop on the initial model:
    told that its validation will take the whole budget, the run takes no step."""
    import time

    seen = []

    def after(path):
        seen.append((path, path.is_file(), path.with_name(path.stem + "_crop.onnx").is_file()))
        return 3600.0  # the caller's validation needs an hour

    model = tmp_path / "m" / "m.onnx"
    config = _config(tmp_path, max_iterations=1000, deadline=time.time() + 1800.0)
    card = train(DEFAULT_CATALOG, model, config, after=after)
    assert seen == [(model, True, True)]  # asked once, with the initial model exported
    assert card["training"]["steps"] == 0
    out = capsys.readouterr()
    assert "kept 36" in out.out + out.err and "validation 3600 s" in out.out + out.err
    # without a deadline nothing is kept and nothing is asked
    train(DEFAULT_CATALOG, tmp_path / "n" / "m.onnx", _config(tmp_path), after=after)
    assert len(seen) == 1
