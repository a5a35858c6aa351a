"""Robustness of the trunk segmentation to another camera: leave-one-image-out IoU of the pixel
classifier on the held-out mangrove photo under photometric and geometric changes, next to Xue
2018's stripping segmentation on the same changed photos.

Usage: python benchmarks/segment_robust.py [--configs aug0 aug4 aug0gw aug4gw] [--eval-width 1152]
                                           [--reps 10]

Prints one JSON object:

* ``views``: for each change (below) and each method, IoU per held-out photo, mean and min.
  Methods: ``pixel_aug{k}[gw]`` -- the pixel classifier trained on the other three photos
  with k random-camera copies per training photo (``train_pixel_classifier(augment=k)``;
  ``gw``: with ``colour_norm="grey_world"``), post-processing by inner leave-one-out on those
  three, exactly as ``segment_real.py``; the held-out photo is never in training and never
  augmented;
  ``xue2018`` / ``full_frame``: the stripping presets.
* ``speed``: images per CPU-second at 1280 x 720 for each classifier trained on all four photos
  (one thread; ``segment_real.speed``).

Changes (applied to the held-out photo only; ``stemmap.vision.photometric``):
white balance, linear-light gains (R, G, B) = (1.2, 1.0, 0.8) and (0.8, 1.0, 1.2); exposure
x0.6 and x1.6 in linear light (clipped); tone curve in^0.6 and in^1.6; hue +-10 degrees; JPEG
quality 30; Gaussian blur sigma 3 and 6 px at the evaluation width (1 and 2 px at the
classifier's 384-px working width); resolution: the photo area-resized from the original
4608 x 3456 to 640 x 480, to the working scale 384 x 288, and centre-cropped to 16:9 and
resized to 1280 x 720; zoom: the central 2/3 of the photo (trunks 1.5x wider in pixels).
For the resolution and zoom views the labels are rasterised at the new size (and cropped).

Data: ../shared/datasets/mangrove (4 phone photos, YOLO polygons, CC BY 4.0), evaluated at
``--eval-width`` pixels wide like ``segment_real.py``.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from segment_real import (
    SOURCE,
    fold_models,
    iou,
    load,
    run_info,
    single_threaded_mangrove,
    speed,
    train,
)
from stemmap.vision import photometric as ph
from stemmap.vision.image_io import read_image
from stemmap.vision.segment import segment_trunks
from stemmap.vision.segment_classifier import PixelModel, read_label_mask, segment_pixels

Pair = tuple[np.ndarray, np.ndarray]

PHOTOMETRIC: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "none": lambda im: im,
    "wb_gains_1.2_1.0_0.8": lambda im: ph.white_balance(im, (1.2, 1.0, 0.8)),
    "wb_gains_0.8_1.0_1.2": lambda im: ph.white_balance(im, (0.8, 1.0, 1.2)),
    "exposure_x0.6": lambda im: ph.exposure(im, 0.6),
    "exposure_x1.6": lambda im: ph.exposure(im, 1.6),
    "gamma_0.6": lambda im: ph.gamma(im, 0.6),
    "gamma_1.6": lambda im: ph.gamma(im, 1.6),
    "hue_+10deg": lambda im: ph.hue_rotate(im, 10.0),
    "hue_-10deg": lambda im: ph.hue_rotate(im, -10.0),
    "jpeg_q30": lambda im: ph.jpeg(im, 30),
    "blur_sigma3px": lambda im: ph.blur(im, 3.0),
    "blur_sigma6px": lambda im: ph.blur(im, 6.0),
}


def _resized(full: np.ndarray, label: Path, w: int, crop_h: int = 0) -> Pair:
    """The photo area-resized to ``w`` pixels wide; ``crop_h`` > 0: then centre-cropped to
    ``crop_h`` rows (labels rasterised at the uncropped size, then cropped)."""
    H, W = full.shape[:2]
    hh = round(H * w / W)
    mask = read_label_mask(label, w, hh)
    img = np.asarray(cv2.resize(full, (w, hh), interpolation=cv2.INTER_AREA), np.uint8)
    if crop_h:
        r0 = (hh - crop_h) // 2
        img, mask = img[r0 : r0 + crop_h], mask[r0 : r0 + crop_h]
    return np.ascontiguousarray(img), np.ascontiguousarray(mask)


def _zoom(full: np.ndarray, label: Path, factor: float, width: int) -> Pair:
    """The central 1/factor of the photo, area-resized to ``width`` pixels wide."""
    H, W = full.shape[:2]
    big_w = round(width * factor)
    img, mask = _resized(full, label, big_w)
    h = round(H * width / W)
    r0, c0 = (img.shape[0] - h) // 2, (big_w - width) // 2
    return (
        np.ascontiguousarray(img[r0 : r0 + h, c0 : c0 + width]),
        np.ascontiguousarray(mask[r0 : r0 + h, c0 : c0 + width]),
    )


def geometric_views(full: np.ndarray, label: Path, eval_width: int) -> dict[str, Pair]:
    return {
        "res_640x480": _resized(full, label, 640),
        "res_384_working_scale": _resized(full, label, 384),
        "res_1280x720_crop16:9": _resized(full, label, 1280, crop_h=720),
        "zoom_1.5x": _zoom(full, label, 1.5, eval_width),
    }


def _summary(per: dict[str, float]) -> dict[str, Any]:
    v = list(per.values())
    return {"per_image": per, "mean": float(np.mean(v)), "min": float(np.min(v))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--eval-width", type=int, default=1152)
    ap.add_argument("--configs", nargs="+", default=["aug0", "aug4", "aug0gw", "aug4gw"])
    ap.add_argument("--reps", type=int, default=10)
    args = ap.parse_args(argv)
    folder = single_threaded_mangrove()
    if folder is None:
        return 0
    t0 = time.perf_counter()
    names, imgs, masks = load(folder, args.eval_width)
    photos = sorted((folder / "images").glob("*.jpg"))
    methods: dict[str, Callable[[int, np.ndarray], np.ndarray]] = {}
    folds: dict[str, list[PixelModel]] = {}
    kws = {}
    for cfg in args.configs:
        m = re.fullmatch(r"aug(\d+)(gw)?", cfg)
        if m is None:
            raise SystemExit(f"config {cfg!r} is not aug<k> or aug<k>gw")
        key = f"pixel_{cfg}"
        kws[key] = {"augment": int(m[1]), "colour_norm": "grey_world" if m[2] else "none"}
        folds[key] = fold_models(imgs, masks, **kws[key])
        methods[key] = lambda i, im, key=key: segment_pixels(im, folds[key][i]).mask
    for preset in ("xue2018", "full_frame"):
        methods[preset] = lambda i, im, preset=preset: segment_trunks(im, preset).mask
    views: dict[str, dict[str, dict[str, float]]] = {}
    for i, (name, f) in enumerate(zip(names, photos, strict=True)):
        pairs = {v: (fn(imgs[i]), masks[i]) for v, fn in PHOTOMETRIC.items()}
        label = folder / "labels" / (f.stem + ".txt")
        pairs.update(geometric_views(read_image(f), label, args.eval_width))
        for view, (im, gt) in pairs.items():
            for meth, fn in methods.items():
                views.setdefault(view, {}).setdefault(meth, {})[name] = iou(fn(i, im), gt)
    finals = {key: train(imgs, masks, meta={"source": SOURCE}, **kws[key]) for key in folds}
    doc = {
        "data": str(folder),
        "eval_width": args.eval_width,
        "images": names,
        "views": {v: {m: _summary(p) for m, p in d.items()} for v, d in views.items()},
        "inner_post": {
            key: {n: m.meta["inner_post"] for n, m in zip(names, ms, strict=True)}
            for key, ms in folds.items()
        },
        "speed": {key: speed(imgs[0], m, args.reps) for key, m in finals.items()},
        **run_info(t0),
    }
    print(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
