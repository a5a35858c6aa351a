"""Trainable pixel classifier for trunks (ilastik-style), the default of ``stemmap segment``.

Pipeline (:func:`segment_pixels`): area-downscale the photo to the model's working width ->
grey-world white balance if the model says so (``colour_norm``; Buchsbaum 1980) -> multi-scale
features (:mod:`stemmap.vision.segment_features`) -> gradient-boosted trees give
P(trunk) per pixel -> threshold, opening, removal of components smaller than a fraction of the
image -> the working-resolution mask is upsampled (bilinear, 0.5) to the photo -> connected
regions with Xue 2018's matching level (eq. 18) so the regions can feed the fusion.

The classifier is scikit-learn's ``HistGradientBoostingClassifier`` (Ke et al. 2017, LightGBM,
histogram split finding; Friedman 2001 gradient boosting with the binary log-loss). After
training, its trees are exported into flat arrays (:class:`TreeEnsemble`) that a compiled
predictor evaluates; a model file is an ``.npz`` of plain numeric arrays plus a JSON header,
loaded with ``allow_pickle=False`` and validated (:func:`load_model`): no pickle anywhere.
Training can add camera-like copies of each photo (``augment``,
:func:`stemmap.vision.photometric.random_camera`) so the model holds under other cameras.
"""

from __future__ import annotations

import json
import logging
import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.io._util import check_npz_sizes
from stemmap.io.atomic import atomic_write
from stemmap.vision.segment import Segmentation, label_regions, yolo_trunk_mask
from stemmap.vision.segment_features import (
    FEATURE_VERSION,
    feature_names,
    pixel_features,
    working_size,
)

__all__ = [
    "MODEL_FORMAT",
    "MODEL_FORMAT_VERSION",
    "PixelModel",
    "TreeEnsemble",
    "default_model",
    "load_model",
    "postprocess",
    "probability_map",
    "read_label_mask",
    "save_model",
    "segment_pixels",
    "train_pixel_classifier",
    "upsample_mask",
]

log = logging.getLogger(__name__)

MODEL_FORMAT = "stemmap-pixel-classifier"
#: Version 2 added ``colour_norm`` (a v1 reader would ignore it: the version keeps v1 readers
#: from applying a grey-world model to raw colours); version 1 files are read as colour_norm
#: "none".
MODEL_FORMAT_VERSION = 2
_READABLE_VERSIONS = (1, 2)
DEFAULT_MODEL_RESOURCE = "mangrove_trunks_v2.npz"
#: Per-image colour normalisation before the features: none, or grey-world white balance.
ColourNorm = Literal["none", "grey_world"]
_ARRAYS = {
    "feature": np.int32,
    "threshold": np.float64,
    "left": np.int32,
    "right": np.int32,
    "missing_left": np.uint8,
    "is_leaf": np.uint8,
    "value": np.float64,
    "roots": np.int64,
}


@dataclass(frozen=True, eq=False)
class TreeEnsemble:
    """Binary gradient-boosted trees in flat arrays (see :mod:`stemmap.vision._tree_kernel`).

    The raw score of a row is ``baseline + sum over trees of the reached leaf value`` (log-odds
    of the positive class, Friedman 2001 eq. 21 with the logistic loss); P = 1 / (1 + e^-raw).
    """

    feature: NDArray[np.int32]
    threshold: NDArray[np.float64]
    left: NDArray[np.int32]
    right: NDArray[np.int32]
    missing_left: NDArray[np.uint8]
    is_leaf: NDArray[np.uint8]
    value: NDArray[np.float64]
    roots: NDArray[np.int64]
    baseline: float

    @property
    def n_nodes(self) -> int:
        return int(self.feature.shape[0])

    def validate(self, n_features: int, where: str = "model") -> None:
        """Raise InputError unless the arrays form well-founded trees over ``n_features``."""
        n = self.n_nodes
        for name, dt in _ARRAYS.items():
            a = getattr(self, name)
            if a.dtype != dt or a.ndim != 1:
                raise InputError(f"{where}: array {name!r} must be 1-D {np.dtype(dt)}.")
            if name != "roots" and a.shape[0] != n:
                raise InputError(f"{where}: array {name!r} has {a.shape[0]} entries, not {n}.")
        if n == 0 or self.roots.shape[0] == 0:
            raise InputError(f"{where}: the model holds no trees.")
        if not math.isfinite(self.baseline) or not np.all(np.isfinite(self.value)):
            raise InputError(f"{where}: non-finite leaf values or baseline.")
        if np.any((self.roots < 0) | (self.roots >= n)):
            raise InputError(f"{where}: a tree root is outside the node arrays.")
        inner = self.is_leaf == 0
        idx = np.arange(n)
        # children after their parent: every descent terminates
        for child in (self.left, self.right):
            c = child[inner]
            if np.any((c <= idx[inner]) | (c >= n)):
                raise InputError(f"{where}: a split points to an invalid child node.")
        f = self.feature[inner]
        if np.any((f < 0) | (f >= n_features)):
            raise InputError(
                f"{where}: a split uses a feature outside 0..{n_features - 1} "
                "(model made for another feature set?)."
            )
        if np.any(np.isnan(self.threshold[inner])):
            raise InputError(f"{where}: a split threshold is NaN.")

    def raw_score(self, X: NDArray[np.float32]) -> NDArray[np.float64]:
        """Log-odds of the positive class for each row of ``X`` (N, F) float32."""
        from stemmap.vision._tree_kernel import forest_raw_score

        return np.asarray(
            forest_raw_score(
                np.ascontiguousarray(X, dtype=np.float32),
                self.feature,
                self.threshold,
                self.left,
                self.right,
                self.missing_left,
                self.is_leaf,
                self.value,
                self.roots,
                float(self.baseline),
            )
        )

    @classmethod
    def from_sklearn(cls, clf: Any) -> TreeEnsemble:
        """Export a fitted binary ``HistGradientBoostingClassifier`` (numerical features only).

        Uses the fitted predictors' node records (``_predictors``); the caller checks the
        export against ``clf.decision_function`` (:func:`train_pixel_classifier` does).
        """
        preds = clf._predictors
        if any(len(p) != 1 for p in preds):
            raise ConfigError("only binary classifiers can be exported.")
        parts: dict[str, list[NDArray[Any]]] = {k: [] for k in _ARRAYS if k != "roots"}
        roots: list[int] = []
        off = 0
        for (tree,) in preds:
            nodes = tree.nodes
            if np.any(nodes["is_categorical"]):
                raise ConfigError("categorical splits are not supported by the export.")
            roots.append(off)
            parts["feature"].append(nodes["feature_idx"].astype(np.int32))
            parts["threshold"].append(nodes["num_threshold"].astype(np.float64))
            parts["left"].append(nodes["left"].astype(np.int32) + off)
            parts["right"].append(nodes["right"].astype(np.int32) + off)
            parts["missing_left"].append(nodes["missing_go_to_left"].astype(np.uint8))
            parts["is_leaf"].append(nodes["is_leaf"].astype(np.uint8))
            parts["value"].append(nodes["value"].astype(np.float64))
            off += len(nodes)
        arrays = {k: np.concatenate(v) for k, v in parts.items()}
        leaf = arrays["is_leaf"].astype(bool)
        for k in ("left", "right"):  # leaves: children unused, zero them for validation
            arrays[k][leaf] = 0
        arrays["feature"][leaf] = 0
        arrays["threshold"][leaf] = 0.0
        base = float(np.asarray(clf._baseline_prediction).reshape(-1)[0])
        return cls(roots=np.asarray(roots, dtype=np.int64), baseline=base, **arrays)


@dataclass(frozen=True, eq=False)
class PixelModel:
    """A trained trunk pixel classifier with its post-processing.

    Attributes
    ----------
    trees : TreeEnsemble
    work_width : int -- features are computed at this width (pixels)
    threshold : float -- P(trunk) above which a pixel is trunk
    open_px : int -- side of the square opening at the working width (0 = none)
    min_area_frac : float -- components smaller than this fraction of the image are dropped
    colour_norm : "none" | "grey_world" -- per-image white balance of the working image before
        the features (:func:`stemmap.vision.photometric.grey_world`); files without the field
        (older models) mean "none"
    meta : dict -- provenance (training images, source, licence, parameters), JSON-serialisable
    """

    trees: TreeEnsemble
    work_width: int = 384
    threshold: float = 0.5
    open_px: int = 3
    min_area_frac: float = 2e-3
    colour_norm: ColourNorm = "none"
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold < 1.0:
            raise ConfigError(f"threshold must be in (0, 1), got {self.threshold}.")
        if self.open_px < 0 or not 0.0 <= self.min_area_frac < 1.0:
            raise ConfigError(
                f"need open_px >= 0 and min_area_frac in [0, 1), got {self.open_px}, "
                f"{self.min_area_frac}."
            )
        if self.work_width < 16:
            raise ConfigError(f"work_width must be >= 16 pixels, got {self.work_width}.")
        if self.colour_norm not in get_args(ColourNorm):
            raise ConfigError(
                f"colour_norm must be one of {get_args(ColourNorm)}, got {self.colour_norm!r}."
            )

    def with_postprocessing(self, **changes: Any) -> PixelModel:
        return replace(self, **changes)


# ---------------------------------------------------------------------------------------------
# Prediction
# ---------------------------------------------------------------------------------------------


def _downscale(rgb: NDArray[np.uint8], work_width: int) -> NDArray[np.uint8]:
    H, W = rgb.shape[:2]
    w, h = working_size(W, H, work_width)
    if (w, h) == (W, H):
        return np.ascontiguousarray(rgb)
    return np.asarray(cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA), dtype=np.uint8)


def _normalise(rgb: NDArray[np.uint8], colour_norm: ColourNorm) -> NDArray[np.uint8]:
    if colour_norm == "grey_world":
        from stemmap.vision.photometric import grey_world

        return grey_world(rgb)
    return rgb


def probability_map(rgb: NDArray[np.uint8], model: PixelModel) -> NDArray[np.float32]:
    """P(trunk) per pixel at the model's working resolution, (h, w) float32."""
    small = _normalise(_downscale(_check_rgb(rgb), model.work_width), model.colour_norm)
    f = pixel_features(small)
    h, w, n_f = f.shape
    raw = model.trees.raw_score(f.reshape(-1, n_f))
    return (1.0 / (1.0 + np.exp(-raw))).astype(np.float32).reshape(h, w)


def postprocess(
    prob: NDArray[np.float32], threshold: float, open_px: int, min_area_frac: float
) -> NDArray[np.bool_]:
    """Threshold, open with a ``open_px`` square, drop components < ``min_area_frac`` x image."""
    m = (prob > threshold).astype(np.uint8)
    if open_px > 1:
        se = cv2.getStructuringElement(cv2.MORPH_RECT, (open_px, open_px))
        m = np.asarray(cv2.morphologyEx(m, cv2.MORPH_OPEN, se), dtype=np.uint8)
    if min_area_frac > 0:
        _, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        keep = stats[:, cv2.CC_STAT_AREA] >= min_area_frac * m.size
        keep[0] = False
        m = keep[lab].astype(np.uint8)
    return m.astype(bool)


def upsample_mask(small: NDArray[np.bool_], shape: tuple[int, int]) -> NDArray[np.bool_]:
    """Bilinear upsampling of a working-resolution mask to ``shape`` (H, W), cut at 0.5."""
    H, W = shape
    if small.shape == (H, W):
        return small
    up = cv2.resize(small.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
    return np.asarray(up > 0.5)


def _check_rgb(rgb: NDArray[np.uint8]) -> NDArray[np.uint8]:
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError(f"image must be (H, W, 3) uint8 RGB, got {img.shape} {img.dtype}.")
    return img


def segment_pixels(rgb: NDArray[np.uint8], model: PixelModel | None = None) -> Segmentation:
    """Segment trunks with the trainable pixel classifier (default: the shipped mangrove model).

    Returns a :class:`~stemmap.vision.segment.Segmentation` at the photo's resolution; every
    kept component is a region (no "taller than wide" rule: leaning stems are trunks too), with
    Xue 2018's matching level (eq. 18, k3 = 2) as alpha.
    """
    img = _check_rgb(rgb)
    m = default_model() if model is None else model
    prob = probability_map(img, m)
    full = upsample_mask(postprocess(prob, m.threshold, m.open_px, m.min_area_frac), img.shape[:2])
    labels, regions = label_regions(full)
    return Segmentation(full, labels, regions, regions)


# ---------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------


def _mask_at(mask: NDArray[np.bool_], w: int, h: int) -> NDArray[np.bool_]:
    if mask.shape == (h, w):
        return mask
    small = cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return np.asarray(small > 0.5)


def training_samples(
    images: Sequence[NDArray[np.uint8]],
    masks: Sequence[NDArray[np.bool_]],
    *,
    work_width: int = 384,
    per_class: int = 15000,
    seed: int = 0,
    augment: int = 0,
    colour_norm: ColourNorm = "none",
) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """Features and labels of up to ``per_class`` random trunk and background pixels per image
    (class-balanced sampling: trunks are a minority of most photos).

    With ``augment`` = k > 0, each image (at the working width) also gets k copies as random
    other cameras would have taken it (:func:`stemmap.vision.photometric.random_camera`: white
    balance, exposure, tone curve, hue, blur, JPEG), and the image's samples are spread evenly
    over the original and its copies (``per_class // (k + 1)`` each), so the training set keeps
    its size. The copies use their own random stream, so ``augment=0`` is unchanged by it.
    ``colour_norm`` is applied to every view after the camera change, as at prediction time.
    """
    from stemmap.vision.photometric import random_camera

    if len(images) != len(masks) or not images:
        raise InputError(f"need as many masks as images (>= 1), got {len(images)}, {len(masks)}.")
    if augment < 0:
        raise ConfigError(f"augment must be >= 0 copies per image, got {augment}.")
    if colour_norm not in get_args(ColourNorm):
        raise ConfigError(
            f"colour_norm must be one of {get_args(ColourNorm)}, got {colour_norm!r}."
        )
    rng = np.random.default_rng(seed)
    aug_rng = np.random.default_rng([seed, 1])
    take = per_class // (augment + 1) if augment else per_class
    xs, ys = [], []
    for k, (img, mk) in enumerate(zip(images, masks, strict=True)):
        small = _downscale(_check_rgb(img), work_width)
        h, w = small.shape[:2]
        if mk.shape != img.shape[:2]:
            raise InputError(
                f"mask {k} has shape {mk.shape}, its image {img.shape[:2]}; they must match."
            )
        y = _mask_at(mk, w, h).reshape(-1)
        views = [small] + [random_camera(small, aug_rng) for _ in range(augment)]
        for view in views:
            f = pixel_features(_normalise(view, colour_norm)).reshape(h * w, -1)
            for cls in (True, False):
                idx = np.flatnonzero(y == cls)
                if idx.size > take:
                    idx = rng.choice(idx, take, replace=False)
                xs.append(f[idx])
                ys.append(np.full(idx.size, cls, np.uint8))
    X, Y = np.concatenate(xs), np.concatenate(ys)
    if Y.min() == Y.max():
        raise InputError("the training masks need both trunk and background pixels.")
    return X, Y


def train_pixel_classifier(
    images: Sequence[NDArray[np.uint8]],
    masks: Sequence[NDArray[np.bool_]],
    *,
    work_width: int = 384,
    per_class: int = 15000,
    max_iter: int = 80,
    max_leaf_nodes: int = 15,
    learning_rate: float = 0.15,
    seed: int = 0,
    augment: int = 4,
    colour_norm: ColourNorm = "grey_world",
    threshold: float = 0.5,
    open_px: int = 3,
    min_area_frac: float = 2e-3,
    meta: dict[str, Any] | None = None,
) -> PixelModel:
    """Train the trunk pixel classifier on RGB images and their bool trunk masks.

    Gradient boosting (``HistGradientBoostingClassifier``, log-loss, no early stopping so the
    result is deterministic for a seed) on :func:`training_samples`. The exported trees are
    checked against scikit-learn's own scores before the model is returned.

    The size (80 trees of <= 15 leaves) was fixed for speed, not tuned on the photos: the
    compiled predictor evaluates trees x depth nodes per pixel, and 1280 x 720 frames must
    segment at >= 2 images/s on one core.

    ``augment`` (random-camera copies per image, :func:`training_samples`) and ``colour_norm``
    (grey-world white balance before the features, Buchsbaum 1980) default to the settings
    of the shipped model: on the mangrove photos, leave one image out, they raised the mean
    IoU from 0.66 to 0.72 and kept it >= 0.65 under white-balance, exposure, tone, hue, blur,
    JPEG and resolution changes where the plain training fell to 0.38 (docs/algorithms/
    vision-fusion.md, "Robustness to other cameras"). ``augment=0, colour_norm="none"`` is
    the earlier training.
    """
    from sklearn.ensemble import HistGradientBoostingClassifier
    from threadpoolctl import threadpool_limits

    X, Y = training_samples(
        images,
        masks,
        work_width=work_width,
        per_class=per_class,
        seed=seed,
        augment=augment,
        colour_norm=colour_norm,
    )
    clf = HistGradientBoostingClassifier(
        max_iter=max_iter,
        max_leaf_nodes=max_leaf_nodes,
        learning_rate=learning_rate,
        l2_regularization=1.0,
        early_stopping=False,
        random_state=seed,
    )
    with threadpool_limits(1):  # OpenMP spin-waits badly on a shared machine; tiny data anyway
        clf.fit(X, Y)
    trees = TreeEnsemble.from_sklearn(clf)
    chk = X[:: max(1, X.shape[0] // 2000)]
    err = float(np.max(np.abs(trees.raw_score(chk) - clf.decision_function(chk))))
    if err > 1e-6:  # pragma: no cover - would mean scikit-learn changed its tree layout
        raise ConfigError(f"tree export disagrees with scikit-learn by {err:g} (log-odds).")
    info = {
        "n_samples": int(X.shape[0]),
        "n_trunk_samples": int(Y.sum()),
        "max_iter": max_iter,
        "max_leaf_nodes": max_leaf_nodes,
        "learning_rate": learning_rate,
        "per_class": per_class,
        "seed": seed,
        "augment": augment,
    }
    return PixelModel(
        trees,
        work_width=work_width,
        threshold=threshold,
        open_px=open_px,
        min_area_frac=min_area_frac,
        colour_norm=colour_norm,
        meta={"training": info, **(meta or {})},
    )


def read_label_mask(path: str | Path, width: int, height: int) -> NDArray[np.bool_]:
    """Trunk mask (height, width) from a label file: a YOLO segmentation ``.txt`` (the union
    of all its class-0 polygons, :func:`stemmap.vision.segment.yolo_trunk_mask`) or a mask
    image (PNG/BMP; nonzero = trunk) of the same size as its photo."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"label file {p} does not exist.")
    if p.suffix.lower() == ".txt":
        return yolo_trunk_mask(p, width, height)
    from stemmap.vision.image_io import read_image

    m = read_image(p).max(axis=2) > 0
    if m.shape != (height, width):
        raise InputError(
            f"mask {p} is {m.shape[1]} x {m.shape[0]} pixels, its photo {width} x {height}; "
            "a mask must have its photo's size."
        )
    return np.asarray(m)


# ---------------------------------------------------------------------------------------------
# Model files (.npz of numeric arrays + JSON header; never pickle)
# ---------------------------------------------------------------------------------------------


def save_model(model: PixelModel, path: str | Path) -> None:
    """Write ``model`` as an ``.npz`` (format ``stemmap-pixel-classifier`` v2)."""
    t = model.trees
    header = {
        "format": MODEL_FORMAT,
        "format_version": MODEL_FORMAT_VERSION,
        "feature_version": FEATURE_VERSION,
        "feature_names": feature_names(),
        "baseline": t.baseline,
        "work_width": model.work_width,
        "threshold": model.threshold,
        "open_px": model.open_px,
        "min_area_frac": model.min_area_frac,
        "colour_norm": model.colour_norm,
        "meta": model.meta,
    }
    blob = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    arrays = {k: getattr(t, k) for k in _ARRAYS}
    with atomic_write(Path(path), "wb") as fh:
        np.savez_compressed(fh, header=blob, **arrays)


def load_model(path: str | Path) -> PixelModel:
    """Read and validate a model written by :func:`save_model` (``allow_pickle=False``).

    Raises
    ------
    InputError
        Not such a file, another format or version, another feature set, or inconsistent trees.
    """
    p = Path(path)
    try:
        loaded = np.load(p, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise InputError(f"{p} is a single .npy array, not a .npz model file.")
        with loaded as z:
            check_npz_sizes(z, p, "model file")
            files = set(z.files)
            missing = ({"header"} | set(_ARRAYS)) - files
            if missing:
                raise InputError(
                    f"{p} is not a stemmap pixel-classifier model (missing {sorted(missing)}); "
                    "make one with `stemmap segment --train ... --model-out FILE`."
                )
            header = json.loads(bytes(z["header"]).decode("utf-8"))
            arrays = {k: np.asarray(z[k]) for k in _ARRAYS}
    except InputError:
        raise
    except FileNotFoundError:
        raise InputError(f"model file {p} does not exist.") from None
    except (
        OSError,
        ValueError,
        KeyError,
        UnicodeDecodeError,
        EOFError,
        zipfile.BadZipFile,
        RecursionError,
    ) as exc:
        raise InputError(f"{p} is not a readable .npz model file: {exc}") from exc
    if not isinstance(header, dict) or header.get("format") != MODEL_FORMAT:
        raise InputError(f"{p}: header format is not {MODEL_FORMAT!r}.")
    version = header.get("format_version")
    if version not in _READABLE_VERSIONS:
        raise InputError(
            f"{p}: model format version {version!r}, this stemmap reads versions "
            f"{', '.join(map(str, _READABLE_VERSIONS))}; retrain with `stemmap segment --train`."
        )
    if version == 1 and "colour_norm" in header:
        raise InputError(f"{p}: a format version 1 model cannot carry colour_norm.")
    if (
        header.get("feature_version") != FEATURE_VERSION
        or header.get("feature_names") != feature_names()
    ):
        raise InputError(
            f"{p}: made for pixel-feature set v{header.get('feature_version')!r}, this stemmap "
            f"computes v{FEATURE_VERSION}; retrain with `stemmap segment --train`."
        )
    try:
        trees = TreeEnsemble(baseline=float(header["baseline"]), **arrays)
        model = PixelModel(
            trees,
            work_width=int(header["work_width"]),
            threshold=float(header["threshold"]),
            open_px=int(header["open_px"]),
            min_area_frac=float(header["min_area_frac"]),
            colour_norm=header.get("colour_norm", "none"),
            meta=dict(header.get("meta", {})),
        )
    except (KeyError, TypeError, ValueError, ConfigError) as exc:
        raise InputError(f"{p}: bad model header field: {exc}") from exc
    trees.validate(len(feature_names()), where=str(p))
    return model


_DEFAULT: list[PixelModel] = []


def default_model() -> PixelModel:
    """The shipped model (trained on the four CC BY 4.0 mangrove photos; see
    ``stemmap/vision/models/NOTICE.md``), loaded once."""
    if not _DEFAULT:
        ref = resources.files("stemmap.vision") / "models" / DEFAULT_MODEL_RESOURCE
        with resources.as_file(ref) as f:
            if not f.is_file():
                raise ConfigError(
                    f"the default segmentation model {DEFAULT_MODEL_RESOURCE} is missing from "
                    "the installed package; reinstall stemmap or pass --model FILE."
                )
            _DEFAULT.append(load_model(f))
    return _DEFAULT[0]
