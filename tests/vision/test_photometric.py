"""Camera-like photometric changes (white balance, exposure, tone, hue, blur, JPEG)."""

from __future__ import annotations

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.vision import photometric as ph
from stemmap.vision.segment_classifier import training_samples


def _photo(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)


def test_identity_settings_keep_the_photo() -> None:
    img = _photo()
    before = img.copy()
    # the 8-bit sRGB decode / encode round trip is exact for every code value
    assert np.array_equal(ph.white_balance(img, (1.0, 1.0, 1.0)), img)
    assert np.array_equal(ph.gamma(img, 1.0), img)
    assert np.array_equal(ph.blur(img, 0.0), img)
    # HSV in float32 and back: at most one code value off
    assert np.abs(ph.hue_rotate(img, 0.0).astype(int) - img).max() <= 1
    assert np.abs(ph.hue_rotate(img, 360.0).astype(int) - img).max() <= 1
    assert np.array_equal(img, before)  # inputs untouched


def test_white_balance_acts_in_linear_light() -> None:
    """Linear gain 0.5 on mid-grey sRGB 188 (linear 0.503) gives linear 0.2515 = sRGB 137;
    a gain on the encoded value would give 94. Gain 2 clips white and 188 at 255."""
    img = np.full((2, 2, 3), 188, np.uint8)
    out = ph.white_balance(img, (0.5, 1.0, 2.0))
    assert out[0, 0].tolist() == [137, 188, 255]
    dark = ph.exposure(img, 0.25)
    assert abs(int(dark[0, 0, 0]) - 99) <= 1  # linear 0.126 -> sRGB 0.388 -> 99


def test_gamma_hue_jpeg_and_blur_change_what_they_should() -> None:
    img = _photo()
    assert np.all(ph.gamma(img, 0.6) >= img)  # x^0.6 >= x on [0, 1]
    assert np.all(ph.gamma(img, 1.6) <= img)
    red = np.zeros((4, 4, 3), np.uint8)
    red[..., 0] = 200
    turned = ph.hue_rotate(red, 120.0)  # red -> green, same value and saturation
    assert turned[0, 0].tolist() == [0, 200, 0]
    smooth = np.tile(np.linspace(0, 255, 64, dtype=np.uint8)[None, :, None], (48, 1, 3))
    assert np.abs(ph.jpeg(smooth, 95).astype(int) - smooth).max() < 12
    assert np.abs(ph.jpeg(img, 30).astype(int) - img).mean() > 20  # noise is destroyed
    assert ph.blur(img, 2.0).std() < 0.5 * img.std()


def test_random_camera_is_seeded_and_varied() -> None:
    img = _photo()
    a = ph.random_camera(img, np.random.default_rng(3))
    b = ph.random_camera(img, np.random.default_rng(3))
    c = ph.random_camera(img, np.random.default_rng(4))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.shape == img.shape and a.dtype == np.uint8


def test_bad_settings_are_errors() -> None:
    img = _photo()
    with pytest.raises(ConfigError):
        ph.white_balance(img, (1.0, 0.0, 1.0))
    with pytest.raises(ConfigError):
        ph.gamma(img, 0.0)
    with pytest.raises(ConfigError):
        ph.jpeg(img, 0)
    with pytest.raises(ConfigError):
        ph.blur(img, -1.0)
    with pytest.raises(ConfigError):
        ph.CameraRanges(wb_gain=0.9)
    with pytest.raises(ConfigError):
        ph.CameraRanges(jpeg_quality=(90, 30))
    with pytest.raises(InputError):
        ph.gamma(img[..., 0], 1.2)


def test_augmented_training_samples_keep_the_size_and_add_new_colours() -> None:
    img = _photo(1)
    mask = np.zeros(img.shape[:2], bool)
    mask[:, 20:30] = True
    x0, y0 = training_samples([img], [mask], per_class=300, augment=0)
    x2, y2 = training_samples([img], [mask], per_class=300, augment=2)
    assert x2.shape == x0.shape and int(y2.sum()) == int(y0.sum()) == 300
    # the augmented copies put colours outside the original's range into the samples
    assert not np.allclose(np.sort(x2[:, 0]), np.sort(x0[:, 0]))
    with pytest.raises(ConfigError):
        training_samples([img], [mask], augment=-1)


def test_grey_world_undoes_white_balance_gains() -> None:
    """A diagonal gain in linear light is removed up to 8-bit rounding (no pixel clips: the
    photo is kept below code 200 so gains <= 1.2 stay under 255)."""
    img = (_photo(2) * (200 / 255)).astype(np.uint8)
    ref = ph.grey_world(img)
    for gains in ((1.2, 1.0, 0.8), (0.8, 1.0, 1.2), (0.7, 0.7, 0.7)):
        out = ph.grey_world(ph.white_balance(img, gains))
        # both results have equal linear channel means; the overall level follows the gains
        lin = ph._TO_LINEAR[out].reshape(-1, 3).mean(axis=0)
        assert np.ptp(lin) < 0.01 * lin.mean()
        if gains[0] == gains[1] == gains[2]:
            continue
        assert np.abs(out.astype(int) - ref).mean() < 2.0, gains
    assert np.array_equal(ph.grey_world(np.zeros((3, 3, 3), np.uint8)), np.zeros((3, 3, 3)))
