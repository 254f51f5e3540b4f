"""sim.backgrounds: clutter behind the parts, seeded, the parts' own pixels kept."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import binary_dilation

from posefuse.sim.backgrounds import Backgrounds, clutter, paste_on_clutter


def _scene(h: int = 64, w: int = 80) -> tuple[np.ndarray, np.ndarray]:
    """A grey render with one bright square part in the middle, and the part's mask."""
    image = np.full((h, w, 3), 90, np.uint8)
    mask = np.zeros((h, w), bool)
    mask[20:44, 25:55] = True
    image[mask] = (200, 180, 40)
    return image, mask


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), p=st.sampled_from([0.0, 0.5, 1.0]))
def test_a_seed_gives_one_image_and_the_stream_advances_alike_whatever_applies(seed, p):
    image, mask = _scene()
    config = Backgrounds(p=p)
    a, b = np.random.default_rng(seed), np.random.default_rng(seed)
    assert np.array_equal(
        paste_on_clutter(image, mask, a, config), paste_on_clutter(image, mask, b, config)
    )
    # the next draw is the same whether the clutter applied or not
    never = np.random.default_rng(seed)
    paste_on_clutter(image, mask, never, Backgrounds(p=0.0))
    assert a.random() == never.random()


def test_the_parts_keep_their_pixels_and_the_rest_is_replaced():
    image, mask = _scene()
    out = paste_on_clutter(image, mask, np.random.default_rng(3), Backgrounds(p=1.0))
    inner = np.zeros_like(mask)
    inner[22:42, 27:53] = True  # two pixels in from the outline: beyond the feathering
    assert np.array_equal(out[inner], image[inner])
    far = ~binary_dilation(mask, iterations=3)  # three pixels around the part left out
    changed = np.any(out[far] != image[far], axis=1)
    assert changed.mean() > 0.9
    # the whole image's clutter is not a flat colour: it has edges to learn from
    background = clutter(64, 80, np.random.default_rng(3), Backgrounds())
    assert np.abs(np.diff(background.astype(float), axis=1)).max() > 20


def test_nothing_applied_is_the_image_itself():
    image, mask = _scene()
    out = paste_on_clutter(image, mask, np.random.default_rng(0), Backgrounds(p=0.0))
    assert out is image


def test_a_soft_alpha_blends_and_bad_input_is_refused():
    image, mask = _scene()
    half = np.full(mask.shape, 0.5, np.float32)
    out = paste_on_clutter(
        image, half, np.random.default_rng(1), Backgrounds(p=1.0, feather_px=0.0)
    )
    stream = np.random.default_rng(1)
    stream.random()  # the coin
    back = clutter(*mask.shape, np.random.default_rng(int(stream.integers(2**31))), Backgrounds())
    expected = np.clip(image * 0.5 + back * 0.5 + 0.5, 0, 255).astype(np.uint8)
    assert np.abs(out.astype(int) - expected.astype(int)).max() <= 1
    with pytest.raises(ValueError, match="does not match"):
        paste_on_clutter(image, mask[:10], np.random.default_rng(0), Backgrounds())
    with pytest.raises(ValueError, match="uint8"):
        paste_on_clutter(image.astype(float), mask, np.random.default_rng(0), Backgrounds())
    with pytest.raises(ValueError, match="p must be"):
        Backgrounds(p=1.5)


def test_the_stage_one_alpha_is_the_instance_map_at_the_input_scale(tmp_path):
    """small_part_alpha resizes a view's instance map as the renderer resizes the image."""
    from types import SimpleNamespace

    from posefuse.sim.train_targets import small_part_alpha

    inst = np.zeros((1, 72, 128), np.uint8)
    inst[0, 20:40, 30:70] = 3
    ts = SimpleNamespace(
        full_inst=inst,
        small_rgb=np.zeros((1, 48, 64, 3), np.uint8),
        meta={"spec": {"small_scale": 0.5}},
    )
    alpha = small_part_alpha(ts, 0)
    assert alpha.shape == (48, 64)
    assert np.all(alpha[10:20, 15:35] == 1.0) and alpha[:9].max() == 0.0
    assert alpha.sum() == pytest.approx(20 * 40 / 4)
    assert np.array_equal(alpha[36:], np.repeat(alpha[35:36], 12, axis=0))  # padded as the input
