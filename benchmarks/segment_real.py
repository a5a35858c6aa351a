"""Trunk segmentation on the real mangrove photos: trainable pixel classifier vs Xue 2018.

Usage: python benchmarks/segment_real.py [--eval-width 1152] [--write-model FILE]
                                         [--augment 4] [--colour-norm none]
       python benchmarks/segment_real.py --compare-forest

Prints one JSON object:

* ``loio``: leave-one-image-out mask IoU of the pixel classifier, per held-out photo and mean.
  In each outer fold the held-out photo is never used: the classifier is trained on the other
  three, and its post-processing (threshold, opening, minimum component size) is chosen by an
  inner leave-one-out over those three only (mean IoU of the inner held-out photos);
* ``xue2018`` / ``full_frame``: the stripping segmentation presets on the same photos;
* ``speed``: images/s at 1280 x 720 (a photo area-resized to that size), one OpenCV thread,
  pixel classifier and Xue preset measured alternately in the same run (the machine is shared:
  the ratio is more meaningful than the absolute numbers);
* ``final``: the post-processing chosen by leave-one-out over all four photos for the model
  trained on all four (the shipped default; ``--write-model`` writes it). That model is trained
  on the full-resolution photos, exactly as ``stemmap segment --train`` does (same trees as
  the command in ``SHIPPED_COMMAND`` with that post-processing).

``--augment`` / ``--colour-norm``: the training settings (``train_pixel_classifier``), default
those of the shipped model; the robustness view of these settings is ``segment_robust.py``.

Data: ../shared/datasets/mangrove (4 phone photos 4608 x 3456, YOLO polygons, class 0 = trunk;
Roboflow "mangrove-detection" v6, CC BY 4.0). Photos and labels are evaluated at ``--eval-width``
pixels wide (area downscaling; polygons rasterised at that size).
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from stemmap.datasets import find_datasets_dir
from stemmap.vision.image_io import read_image
from stemmap.vision.segment import evaluate_segmentation, segment_trunks
from stemmap.vision.segment_classifier import (
    PixelModel,
    postprocess,
    probability_map,
    read_label_mask,
    save_model,
    segment_pixels,
    train_pixel_classifier,
    upsample_mask,
)

THRESHOLDS = (0.3, 0.4, 0.5, 0.6, 0.7)
OPEN_PX = (0, 3)
MIN_AREA = (0.0, 2e-3, 1e-2)
#: Training settings of the shipped model (chosen in docs/algorithms/vision-fusion.md,
#: "Robustness to other cameras").
SHIPPED = {"augment": 4, "colour_norm": "grey_world"}
SHIPPED_COMMAND = (
    "stemmap segment --train {data}/images --labels {data}/labels --model-out FILE "
    "--augment {augment} --colour-norm {colour_norm} --threshold {threshold} "
    "--open-px {open_px} --min-area {min_area_frac}"
)
SOURCE = {
    "dataset": "Mangrove Detection v6 (Roboflow Universe, workspace mangrove-xg0rl)",
    "url": "https://universe.roboflow.com/mangrove-xg0rl/mangrove-detection-d0ram/dataset/6",
    "license": "CC BY 4.0",
}


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return evaluate_segmentation(a, [b])["iou"]


def load(folder: Path, width: int) -> tuple[list[str], list[np.ndarray], list[np.ndarray]]:
    names, imgs, masks = [], [], []
    for f in sorted((folder / "images").glob("*.jpg")):
        rgb = read_image(f)
        h = round(rgb.shape[0] * width / rgb.shape[1])
        small = np.ascontiguousarray(
            cv2.resize(rgb, (width, h), interpolation=cv2.INTER_AREA), dtype=np.uint8
        )
        names.append(f.name.split("_")[0])
        imgs.append(small)
        masks.append(read_label_mask(folder / "labels" / (f.stem + ".txt"), width, h))
    if not names:
        raise SystemExit(f"no images/*.jpg under {folder}")
    return names, imgs, masks


def load_full(folder: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The photos at full resolution and their masks, as ``stemmap segment --train`` reads them."""
    imgs, masks = [], []
    for f in sorted((folder / "images").glob("*.jpg")):
        rgb = read_image(f)
        imgs.append(rgb)
        masks.append(read_label_mask(folder / "labels" / (f.stem + ".txt"), *rgb.shape[1::-1]))
    return imgs, masks


def choose_post(probs: list[np.ndarray], masks: list[np.ndarray]) -> dict[str, Any]:
    """Post-processing maximising the mean IoU over (out-of-sample probability map, mask)."""
    best: dict[str, Any] = {"mean_iou": -1.0}
    for t, o, a in itertools.product(THRESHOLDS, OPEN_PX, MIN_AREA):
        ious = [
            iou(upsample_mask(postprocess(p, t, o, a), m.shape), m)
            for p, m in zip(probs, masks, strict=True)
        ]
        if float(np.mean(ious)) > best["mean_iou"]:
            best = {"threshold": t, "open_px": o, "min_area_frac": a}
            best["mean_iou"] = float(np.mean(ious))
    return best


def train(imgs: list[np.ndarray], masks: list[np.ndarray], **kw: Any) -> PixelModel:
    return train_pixel_classifier(imgs, masks, **kw)


def fold_models(
    imgs: list[np.ndarray], masks: list[np.ndarray], **train_kw: Any
) -> list[PixelModel]:
    """Model ``i`` is trained on every photo but ``i``, with the post-processing chosen by an
    inner leave-one-out over those photos (``meta["inner_post"]``); photo ``i`` is never used."""
    models = []
    for i in range(len(imgs)):
        tr = [j for j in range(len(imgs)) if j != i]
        inner_p, inner_m = [], []
        for j in tr:
            sub = [k for k in tr if k != j]
            m = train([imgs[k] for k in sub], [masks[k] for k in sub], **train_kw)
            inner_p.append(probability_map(imgs[j], m))
            inner_m.append(masks[j])
        post = choose_post(inner_p, inner_m)
        model = train([imgs[k] for k in tr], [masks[k] for k in tr], **train_kw)
        model = model.with_postprocessing(
            threshold=post["threshold"],
            open_px=post["open_px"],
            min_area_frac=post["min_area_frac"],
            meta={**model.meta, "inner_post": post},
        )
        models.append(model)
    return models


def loio(
    names: list[str], imgs: list[np.ndarray], masks: list[np.ndarray], **train_kw: Any
) -> dict[str, Any]:
    per: dict[str, Any] = {}
    oof_probs: list[np.ndarray] = []
    for i, model in enumerate(fold_models(imgs, masks, **train_kw)):
        prob = probability_map(imgs[i], model)
        oof_probs.append(prob)
        pred = upsample_mask(
            postprocess(prob, model.threshold, model.open_px, model.min_area_frac),
            masks[i].shape,
        )
        per[names[i]] = {
            "iou": iou(pred, masks[i]),
            "iou_at_0.5_no_post": iou(upsample_mask(prob > 0.5, masks[i].shape), masks[i]),
            "post": model.meta["inner_post"],
        }
    return {
        "per_image": per,
        "mean_iou": float(np.mean([v["iou"] for v in per.values()])),
        "mean_iou_at_0.5_no_post": float(np.mean([v["iou_at_0.5_no_post"] for v in per.values()])),
        "_oof": oof_probs,
    }


def xue(names: list[str], imgs: list[np.ndarray], masks: list[np.ndarray]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for preset in ("xue2018", "full_frame"):
        per = {
            n: iou(segment_trunks(im, preset).mask, m)
            for n, im, m in zip(names, imgs, masks, strict=True)
        }
        out[preset] = {"per_image": per, "mean_iou": float(np.mean(list(per.values())))}
    return out


def compare_forest(
    names: list[str], imgs: list[np.ndarray], masks: list[np.ndarray]
) -> dict[str, Any]:
    """Classifier choice: the same features and samples, scikit-learn random forest (ilastik's
    classifier; 100 trees, min 5 samples per leaf) vs our gradient boosting, leave-one-image-out
    with fixed post-processing (P > 0.5, opening 3 px, min area 0.2 %); CPU seconds to classify
    the pixels of one 1280 x 720 frame (384 x 216 working pixels). Both with the v1 training
    (no augmentation, raw colours), as when the choice was made."""
    from sklearn.ensemble import RandomForestClassifier

    from stemmap.vision.segment_classifier import _downscale, training_samples
    from stemmap.vision.segment_features import pixel_features

    res: dict[str, Any] = {"random_forest": {}, "gradient_boosting": {}}
    frame = np.ascontiguousarray(
        cv2.resize(imgs[0], (1280, 720), interpolation=cv2.INTER_AREA), dtype=np.uint8
    )
    ff = pixel_features(_downscale(frame, 384))
    ff = ff.reshape(-1, ff.shape[2])
    cpu: dict[str, float] = {"random_forest": 0.0, "gradient_boosting": 0.0}
    for i in range(len(imgs)):
        tr = [k for k in range(len(imgs)) if k != i]
        X, Y = training_samples([imgs[k] for k in tr], [masks[k] for k in tr])
        rf = RandomForestClassifier(n_estimators=100, min_samples_leaf=5, n_jobs=1, random_state=0)
        rf.fit(X, Y)
        # the v1 training: the same plain samples as the forest (no augmentation, raw colours)
        gb = train([imgs[k] for k in tr], [masks[k] for k in tr], augment=0, colour_norm="none")
        small = pixel_features(_downscale(imgs[i], 384))
        h, w, nf = small.shape
        p_rf = rf.predict_proba(small.reshape(-1, nf))[:, 1].reshape(h, w).astype(np.float32)
        p_gb = probability_map(imgs[i], gb)
        for key, prob in (("random_forest", p_rf), ("gradient_boosting", p_gb)):
            pred = upsample_mask(postprocess(prob, 0.5, 3, 2e-3), masks[i].shape)
            res[key][names[i]] = iou(pred, masks[i])
        c0 = time.process_time()
        rf.predict_proba(ff)
        c1 = time.process_time()
        gb.trees.raw_score(ff)
        c2 = time.process_time()
        cpu["random_forest"] += c1 - c0
        cpu["gradient_boosting"] += c2 - c1
    for key in res:
        res[key] = {
            "per_image": res[key],
            "mean_iou": float(np.mean(list(res[key].values()))),
            "classify_cpu_s_per_1280x720": cpu[key] / len(imgs),
        }
    return res


def speed(img: np.ndarray, model: PixelModel, reps: int) -> dict[str, Any]:
    frame = np.ascontiguousarray(
        cv2.resize(img, (1280, 720), interpolation=cv2.INTER_AREA), dtype=np.uint8
    )
    segment_pixels(frame, model)  # compile / warm up
    wall = {"px": 0.0, "xue": 0.0}
    cpu = {"px": 0.0, "xue": 0.0}
    for _ in range(reps):
        for key, fn in (
            ("px", lambda: segment_pixels(frame, model)),
            ("xue", lambda: segment_trunks(frame, "xue2018")),
        ):
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall[key] += time.perf_counter() - w0
            cpu[key] += time.process_time() - c0
    return {
        "size": [1280, 720],
        "reps": reps,
        "pixel_classifier_images_per_s_wall": reps / wall["px"],
        "pixel_classifier_images_per_cpu_s": reps / cpu["px"],
        "xue2018_images_per_s_wall": reps / wall["xue"],
        "xue2018_images_per_cpu_s": reps / cpu["xue"],
        "note": "one thread; CPU seconds of this process (the machine was shared and loaded)",
    }


def single_threaded_mangrove() -> Path | None:
    """One OpenCV / BLAS / OpenMP thread; the mangrove folder, or None (a "skipped" JSON
    printed) when the shared datasets are not there."""
    cv2.setNumThreads(1)
    threadpool_limits(1)
    root = find_datasets_dir()
    if root is None or not (root / "mangrove").is_dir():
        print(json.dumps({"skipped": "no shared/datasets/mangrove (set STEMMAP_DATASETS)"}))
        return None
    return root / "mangrove"


def run_info(t0: float) -> dict[str, Any]:
    """Wall time since ``t0`` (perf_counter), Python version and machine of this run."""
    return {
        "wall_s": time.perf_counter() - t0,
        "python": sys.version.split()[0],
        "machine": platform.machine(),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--eval-width", type=int, default=1152)
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--write-model", type=Path, default=None)
    ap.add_argument("--augment", type=int, default=SHIPPED["augment"])
    ap.add_argument("--colour-norm", default=SHIPPED["colour_norm"])
    ap.add_argument(
        "--compare-forest", action="store_true", help="only the random-forest comparison"
    )
    args = ap.parse_args(argv)
    folder = single_threaded_mangrove()
    if folder is None:
        return 0
    root = folder.parent
    t0 = time.perf_counter()
    names, imgs, masks = load(folder, args.eval_width)
    if args.compare_forest:
        print(json.dumps({"classifier_choice": compare_forest(names, imgs, masks)}, indent=2))
        return 0
    settings = {"augment": args.augment, "colour_norm": args.colour_norm}
    res_loio = loio(names, imgs, masks, **settings)
    oof = res_loio.pop("_oof")
    final_post = choose_post(oof, masks)
    full_imgs, full_masks = load_full(root / "mangrove")
    final = train(full_imgs, full_masks, meta={"source": SOURCE, "trained_on": names}, **settings)
    del full_imgs, full_masks
    final = final.with_postprocessing(
        threshold=final_post["threshold"],
        open_px=final_post["open_px"],
        min_area_frac=final_post["min_area_frac"],
    )
    if args.write_model is not None:
        save_model(final, args.write_model)
    doc = {
        "data": str(root / "mangrove"),
        "eval_width": args.eval_width,
        "images": names,
        "loio": res_loio,
        **xue(names, imgs, masks),
        "final": {
            "settings": settings,
            "post": final_post,
            "n_nodes": final.trees.n_nodes,
            "command": SHIPPED_COMMAND.format(data=root / "mangrove", **settings, **final_post),
        },
        "speed": speed(imgs[0], final, args.reps),
        **run_info(t0),
    }
    print(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
