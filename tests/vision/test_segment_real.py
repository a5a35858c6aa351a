"""Pixel classifier on the real mangrove photos (../shared/datasets/mangrove, CC BY 4.0)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from stemmap.datasets import find_datasets_dir
from stemmap.vision import photometric as ph
from stemmap.vision.image_io import read_image
from stemmap.vision.segment import segment_trunks
from stemmap.vision.segment_classifier import (
    PixelModel,
    default_model,
    load_model,
    read_label_mask,
    segment_pixels,
    train_pixel_classifier,
)

pytestmark = pytest.mark.slow
WIDTH = 768


def _mangrove() -> Path:
    root = find_datasets_dir()
    if root is None or not (root / "mangrove" / "images").is_dir():
        pytest.skip("shared/datasets/mangrove not available")
    return root / "mangrove"


@pytest.fixture(scope="module")
def photos() -> list[tuple[str, np.ndarray, np.ndarray]]:
    root = _mangrove()
    out = []
    for f in sorted((root / "images").glob("*.jpg")):
        rgb = read_image(f)
        h = round(rgb.shape[0] * WIDTH / rgb.shape[1])
        small = np.asarray(cv2.resize(rgb, (WIDTH, h), interpolation=cv2.INTER_AREA), np.uint8)
        gt = read_label_mask(root / "labels" / (f.stem + ".txt"), WIDTH, h)
        out.append((f.name[:3], small, gt))
    assert len(out) == 4
    return out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(int((a | b).sum()), 1))


def _hold_out_005(photos, **settings: Any) -> tuple[str, np.ndarray, np.ndarray, PixelModel]:
    """A smaller model than the shipped one (test time) trained on 006, 008, 033; 005 kept."""
    train = photos[1:]
    name, img, gt = photos[0]
    model = train_pixel_classifier(
        [p[1] for p in train], [p[2] for p in train], per_class=6000, max_iter=50, **settings
    )
    return name, img, gt, model


def test_held_out_photo_after_training_on_the_others(photos) -> None:
    """Train (smaller model than the shipped one, for test time) on photos 006, 008, 033 and
    segment 005, never seen: IoU 0.68 when written (full_frame preset 0.35); the bound is the
    issue's 0.5 target. benchmarks/segment_real.py gives 0.62 for this fold with the full model
    and its inner-CV post-processing."""
    name, img, gt, model = _hold_out_005(photos, augment=0, colour_norm="none")
    iou = _iou(segment_pixels(img, model).mask, gt)
    assert iou > 0.5, (name, iou)
    assert iou > _iou(segment_trunks(img, "full_frame").mask, gt) + 0.1


def test_shipped_model_on_real_crops(photos) -> None:
    """The shipped model loads and segments 1280 x 720-like crops of the photos (its training
    photos: a regression check of the file, not a held-out score -- that is the test above and
    the benchmark's leave-one-image-out table)."""
    model = default_model()
    assert model.meta["source"]["license"] == "CC BY 4.0"
    for name, img, gt in photos:
        crop = (slice(0, 432), slice(0, 768))  # 16:9 crop of the top of the photo
        iou = _iou(segment_pixels(np.ascontiguousarray(img[crop]), model).mask, gt[crop])
        assert iou > 0.7, (name, iou)  # 0.78-0.86 with the v2 model (0.85-0.88 with v1)


def test_held_out_photo_under_another_cameras_colours(photos) -> None:
    """The shipped training settings (4 random-camera copies per photo, grey-world colour
    normalisation; smaller model for test time) trained on 006, 008, 033; the held-out 005 is
    changed as another camera would: white-balance gains (R, G, B) = (0.8, 1, 1.2) and
    (1.2, 1, 0.8), tone curve in^1.6, hue +10 degrees. Measured when written: IoU 0.584,
    0.757, 0.641, 0.688 (0.687 unchanged); the bound is the issue's 0.5 target, 0.08 below the
    worst. The previous training (no augmentation, raw colours) gave 0.037, 0.688, 0.404,
    0.353 here: it collapsed under the bluer white balance."""
    name, img, gt, model = _hold_out_005(photos, augment=4, colour_norm="grey_world")
    views = {
        "wb_0.8_1_1.2": ph.white_balance(img, (0.8, 1.0, 1.2)),
        "wb_1.2_1_0.8": ph.white_balance(img, (1.2, 1.0, 0.8)),
        "gamma_1.6": ph.gamma(img, 1.6),
        "hue_+10": ph.hue_rotate(img, 10.0),
    }
    ious = {v: _iou(segment_pixels(im, model).mask, gt) for v, im in views.items()}
    assert min(ious.values()) > 0.5, (name, ious)


def test_shipped_model_is_what_the_training_command_makes(tmp_path: Path) -> None:
    """docs/datasets.md's command (the CLI's training defaults: 4 random-camera copies,
    grey-world colours; the post-processing chosen by benchmarks/segment_real.py) rebuilds the
    shipped trees bit for bit (seeded sampling and augmentation, single-threaded fit)."""
    from typer.testing import CliRunner

    from stemmap.cli import app

    root = _mangrove()
    out = tmp_path / "m.npz"
    res = CliRunner().invoke(
        app,
        ["segment", "--train", str(root / "images"), "--labels", str(root / "labels"),
         "--model-out", str(out), "--threshold", "0.7", "--open-px", "3", "--min-area", "0.002"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    made, shipped = load_model(out), default_model()
    for k in ("feature", "threshold", "left", "right", "missing_left", "is_leaf", "value"):
        np.testing.assert_array_equal(getattr(made.trees, k), getattr(shipped.trees, k), k)
    assert made.trees.baseline == shipped.trees.baseline
    got = (made.threshold, made.open_px, made.min_area_frac, made.colour_norm)
    assert got == (shipped.threshold, shipped.open_px, shipped.min_area_frac, "grey_world")
