"""A training set for another detector input scale is the set a rendering at that scale writes,
made from the full views already rendered."""

from __future__ import annotations

import json

import numpy as np

from posefuse.service.resources import DEFAULT_CATALOG
from posefuse.sim.train_data import RenderSpec, render_training_set


def test_a_set_at_another_input_scale_is_resized_not_rendered_and_equals_a_rendering(tmp_path):
    spec = RenderSpec(n_scenes=1, views=1, seed_base=123, robi_fraction=0.0)
    half = render_training_set(DEFAULT_CATALOG, spec, tmp_path / "a", workers=1)
    wider = RenderSpec(n_scenes=1, views=1, seed_base=123, robi_fraction=0.0, small_scale=0.625)
    derived = render_training_set(DEFAULT_CATALOG, wider, tmp_path / "a", workers=1)
    assert derived.meta["rescaled_from"] == str(half.folder)
    assert derived.small_rgb.shape == (1, 464, 800, 3) and derived.meta["small_size"] == [800, 464]
    rendered = render_training_set(DEFAULT_CATALOG, wider, tmp_path / "b", workers=1)
    assert "rescaled_from" not in rendered.meta
    assert np.array_equal(derived.small_rgb, rendered.small_rgb)
    assert np.array_equal(derived.full_rgb, rendered.full_rgb)
    assert np.array_equal(derived.instances, rendered.instances)
    assert derived.meta["spec"] == rendered.meta["spec"]
    # a set of another spec is not taken for a rescaling
    other = RenderSpec(n_scenes=1, views=1, seed_base=124, robi_fraction=0.0, small_scale=0.625)
    fresh = render_training_set(DEFAULT_CATALOG, other, tmp_path / "a", workers=1)
    assert "rescaled_from" not in json.loads((fresh.folder / "meta.json").read_text())
