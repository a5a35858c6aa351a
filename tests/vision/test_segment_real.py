"""Pixel classifier on the real mangrove photos (../shared/datasets/mangrove, CC BY 4.0)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stemmap.datasets import find_datasets_dir
from stemmap.vision.image_io import read_image
from stemmap.vision.segment import segment_trunks
from stemmap.vision.segment_classifier import (
    default_model,
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


def test_held_out_photo_after_training_on_the_others(photos) -> None:
    """Train (smaller model than the shipped one, for test time) on photos 006, 008, 033 and
    segment 005, never seen: IoU 0.68 when written (full_frame preset 0.35); the bound is the
    issue's 0.5 target. benchmarks/segment_real.py gives 0.62 for this fold with the full model
    and its inner-CV post-processing."""
    train = photos[1:]
    name, img, gt = photos[0]
    model = train_pixel_classifier(
        [p[1] for p in train], [p[2] for p in train], per_class=6000, max_iter=50
    )
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
        assert iou > 0.7, (name, iou)  # 0.85-0.88 when written
