"""A real camera's effects on training samples: seeded, bounded, and each of them visible."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posefuse.sim.photometric import Photometric, photometric


def _image(seed: int = 0) -> np.ndarray:
    """A grey bin floor with a bright part: edges, flat areas, both ends of the range."""
    rng = np.random.default_rng(seed)
    image = np.full((64, 80, 3), 110, np.uint8)
    cv2.circle(image, (40, 32), 16, (230, 225, 210), -1)
    image[:, :8] = 20
    return np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 1.0))
def test_a_seed_gives_one_image_and_the_stream_advances_alike_whatever_applies(seed, p):
    image = _image()
    a = photometric(image, np.random.default_rng(seed), Photometric(p=p))
    rng = np.random.default_rng(seed)
    b = photometric(image, rng, Photometric(p=p))
    assert a.dtype == np.uint8 and a.shape == image.shape
    assert np.array_equal(a, b)
    # the draws do not depend on which effects applied: the stream after the call is the same
    other = np.random.default_rng(seed)
    photometric(image, other, Photometric(p=1.0 - p))
    assert rng.random() == other.random()


def test_nothing_applied_is_the_image_itself():
    image = _image()
    out = photometric(image, np.random.default_rng(3), Photometric(p=0.0))
    assert np.array_equal(out, image) and out is not image


def test_each_effect_shows():
    image = _image()

    def only(**kw):
        base = dict(gain_log=0.0, white_balance_log=0.0, gamma_log=0.0)
        base.update(blur_sigma=(1e-3, 1e-3), noise_std=(0.0, 0.0), jpeg_quality=(100, 100))
        base.update(kw)
        return [
            photometric(image, np.random.default_rng(s), Photometric(p=1.0, **base))
            for s in range(8)
        ]

    # exposure and white balance move the mean, per channel apart
    means = np.array([o.reshape(-1, 3).mean(0) for o in only(gain_log=0.5, white_balance_log=0.2)])
    assert np.ptp(means[:, 0]) > 10 and np.ptp(means[:, 0] - means[:, 1]) > 2
    # blur lowers the gradient energy
    sharp = np.abs(np.diff(image.astype(float), axis=1)).mean()
    blurred = [np.abs(np.diff(o.astype(float), axis=1)).mean() for o in only(blur_sigma=(1.5, 1.5))]
    assert max(blurred) < 0.8 * sharp
    # noise raises the variance of a flat area
    flat = [o[5:25, 12:30].astype(float).std() for o in only(noise_std=(8.0, 8.0))]
    assert min(flat) > 5.0
    # JPEG at low quality leaves its blocks: the image differs, its mean barely
    jpeg = only(jpeg_quality=(10, 10))
    assert all(np.abs(o.astype(int) - image).mean() > 0.5 for o in jpeg)
    assert all(abs(o.mean() - image.mean()) < 3 for o in jpeg)


def test_bad_input_and_ranges_are_refused():
    with pytest.raises(ValueError, match="uint8"):
        photometric(np.zeros((4, 4, 3), np.float32), np.random.default_rng(0), Photometric())
    with pytest.raises(ValueError, match="p must be in"):
        Photometric(p=1.5)
    with pytest.raises(ValueError, match="jpeg_quality"):
        Photometric(jpeg_quality=(0, 90))
