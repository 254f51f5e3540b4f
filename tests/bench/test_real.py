"""bench.real: a dataset and its rendered twin, side by side, per front end."""

import json

from posefuse.bench import real


def test_a_dataset_and_its_twin_side_by_side(small_dataset_root, tmp_path, capsys):
    out = tmp_path / "rates.json"
    assert (
        real.main(
            [
                "--real",
                str(small_dataset_root),
                "--out",
                str(tmp_path),
                "--json",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    rates = json.loads(out.read_text())
    assert set(rates) == {
        f"{f} / {d}"
        for f in ("oracle, silhouettes", "oracle, boxes")
        for d in ("real", "rendered twin")
    }
    for row in rates.values():
        assert set(row) == {"2"}  # 3 views a scene: the 2-view checkpoint only
        assert row["2"]["instances"] > 0 and 0.0 <= row["2"]["add_sym"] <= 1.0
    printed = capsys.readouterr().out
    assert "| oracle, boxes | rendered twin |" in printed and "per object at 4 views" in printed
    assert (tmp_path / "twin" / "camera.json").is_file()  # rendered where it was missing


def test_a_part_sets_network_is_scored_as_a_front_end_on_both(small_dataset_root, tmp_path, capsys):
    """With --parts, the network's rows and its front end's recall and precision on the real
    dataset and on its twin (here a part set whose model is the shipped one, of the shipped
    catalog the small dataset is rendered from)."""
    from posefuse.service.resources import DEFAULT_MODEL
    from posefuse.sim.onboard import MANIFEST, MANIFEST_VERSION

    parts = tmp_path / "parts"
    parts.mkdir()
    manifest = {"version": MANIFEST_VERSION, "catalog": ".", "model": str(DEFAULT_MODEL)}
    (parts / MANIFEST).write_text(json.dumps(manifest))
    out = tmp_path / "rates.json"
    args = ["--real", str(small_dataset_root), "--parts", str(parts), "--out", str(tmp_path)]
    assert real.main([*args, "--json", str(out), "--quiet"]) == 0
    rates = json.loads(out.read_text())
    assert {"network / real", "network / rendered twin"} <= set(rates)
    for label in ("real", "rendered twin"):
        score = rates[f"network front end / {label}"]
        assert 0.5 <= score["recall"] <= 1.0 and 0.5 <= score["precision"] <= 1.0, score
    assert "| rendered twin | " in capsys.readouterr().out


def test_a_networks_rows_take_the_settings_of_its_card(small_dataset_root):
    """The network's rows are run with what its card gives the estimator (here the shipped
    card's shared centre error), as run-dataset and the daemon run it; an oracle's with the
    defaults."""
    from posefuse.estimator.frontend.network import NetworkFrontend
    from posefuse.estimator.tracker import TrackerConfig
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.run_dataset import LabelledNetworkFrontend
    from posefuse.service.resources import DEFAULT_MODEL

    dataset = load_dataset(small_dataset_root)
    network = NetworkFrontend(str(DEFAULT_MODEL), dataset.catalog)
    config = real.estimator_config(LabelledNetworkFrontend(dataset, network))
    assert config == TrackerConfig().with_card(network.card.verification)
    assert config.translation_shared_frac == network.card.verification["translation_shared_frac"]
    oracle = real._frontends(dataset, None)["oracle, boxes"]
    assert real.estimator_config(oracle) == TrackerConfig()
