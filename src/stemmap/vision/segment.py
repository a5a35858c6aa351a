"""Stripping segmentation of trunks in colour images (Xue et al. 2018, §2.4.3 and §3.2.2).

The image is stripped part by part of what is not trunk: the canopy (region crop), soil and
bright background (RGB rules), then small or wide blobs (morphology, labelling, the
"taller than wide" rule). Each remaining region gets the matching level
alpha = min(1, k3 A_B / A_BB) (eq. 18), the evidence of :func:`stemmap.fusion.bpa.vision_bpa`.

Images are ``(H, W, 3)`` uint8 arrays in **RGB** order (convert OpenCV's BGR with
``img[..., ::-1]``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

__all__ = [
    "PRESETS",
    "Regions",
    "SegmentParams",
    "Segmentation",
    "evaluate_mangrove",
    "evaluate_segmentation",
    "label_regions",
    "matching_level",
    "read_yolo_polygons",
    "read_yolo_vertices",
    "rgb_trunk_mask",
    "segment_trunks",
    "with_params",
    "yolo_trunk_mask",
]


@dataclass(frozen=True)
class SegmentParams:
    """Parameters of the stripping segmentation.

    Parameters
    ----------
    crop_top : float in [0, 1)
        Fraction of rows removed from the top (canopy). Xue §3.2.2 keeps 540 of 720 rows: 0.25.
    max_channel : int
        Trunk pixels have every channel below this (Xue: 200).
    min_channel : int
        A pixel with any channel below this is soil / shadow (Xue: 50).
    blue_le_green : bool
        Require B <= G + blue_margin (Xue: "blue almost less than green").
    blue_margin : int
        Tolerance of that rule ("almost"): 0 in the strict reading.
    green_excess : int or None
        Strip green plants: G - R > green_excess is vegetation. The paper strips "green plants"
        (§2.4.3) but prints no rule; 15 is our choice. None disables it.
    kernel : int
        Side (pixels, at a 1280-pixel-wide image; scaled with the width) of the square
        structuring element of the open / close operations. Not printed; 5 is our choice.
    min_area_frac : float
        Regions smaller than this fraction of the cropped image are discarded (noise).
    k3 : float
        Gain of eq. 18 (Xue: 2).
    taller_than_wide : bool
        Keep only regions whose bounding box is taller than wide (Xue §3.2.2).
    """

    crop_top: float = 0.25
    max_channel: int = 200
    min_channel: int = 50
    blue_le_green: bool = True
    blue_margin: int = 0
    green_excess: int | None = 15
    kernel: int = 5
    min_area_frac: float = 5e-4
    k3: float = 2.0
    taller_than_wide: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.crop_top < 1.0:
            raise ConfigError(f"crop_top must be in [0, 1), got {self.crop_top}.")
        if not 0 <= self.min_channel < self.max_channel <= 256:
            raise ConfigError(
                f"need 0 <= min_channel < max_channel <= 256, got {self.min_channel}, "
                f"{self.max_channel}."
            )
        if self.kernel < 1:
            raise ConfigError(f"kernel must be >= 1 pixel, got {self.kernel}.")
        if not self.k3 > 0:
            raise ConfigError(f"k3 must be > 0, got {self.k3}.")
        if not 0.0 <= self.min_area_frac < 1.0:
            raise ConfigError(f"min_area_frac must be in [0, 1), got {self.min_area_frac}.")


#: ``xue2018``: the paper's rules and k3; ``xue2018_strict``: without our green-plant rule;
#: ``full_frame``: no canopy crop (photos where trunks fill the frame, e.g. the mangrove set).
PRESETS: dict[str, SegmentParams] = {
    "xue2018": SegmentParams(),
    "xue2018_strict": SegmentParams(green_excess=None),
    "full_frame": SegmentParams(crop_top=0.0),
}


def _params(p: SegmentParams | str | None) -> SegmentParams:
    if p is None:
        return PRESETS["xue2018"]
    if isinstance(p, str):
        try:
            return PRESETS[p]
        except KeyError:
            raise ConfigError(
                f"unknown segmentation preset {p!r}; choose one of {sorted(PRESETS)}."
            ) from None
    return p


def _check_image(image: ArrayLike) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"image must have shape (H, W, 3) (RGB), got {img.shape}.")
    if img.dtype != np.uint8:
        raise InputError(f"image must be uint8, got {img.dtype}.")
    return img


def rgb_trunk_mask(
    image: ArrayLike, params: SegmentParams | str | None = None
) -> NDArray[np.bool_]:
    """Pixels passing Xue's RGB rules (§3.2.2): all channels < 200, B <= G, none < 50;
    plus the green-plant strip G - R > green_excess when enabled.

    Parameters
    ----------
    image : (H, W, 3) uint8 RGB

    Returns
    -------
    (H, W) bool
    """
    p = _params(params)
    img = _check_image(image)
    r = img[..., 0].astype(np.int16)
    g = img[..., 1].astype(np.int16)
    b = img[..., 2].astype(np.int16)
    mx = np.maximum(np.maximum(r, g), b)
    mn = np.minimum(np.minimum(r, g), b)
    m = (mx < p.max_channel) & (mn >= p.min_channel)
    if p.blue_le_green:
        m &= b <= g + p.blue_margin
    if p.green_excess is not None:
        m &= (g - r) <= p.green_excess
    return np.asarray(m)


def matching_level(area: ArrayLike, bbox_area: ArrayLike, k3: float = 2.0) -> FloatArray:
    """Matching level alpha = min(1, k3 A_B / A_BB) (Xue et al. 2018, eq. 18).

    Examples
    --------
    >>> matching_level([320, 900], [1000, 1000]).tolist()
    [0.64, 1.0]
    """
    a = np.asarray(area, dtype=np.float64)
    bb = np.asarray(bbox_area, dtype=np.float64)
    if np.any(bb <= 0) or np.any(a < 0) or np.any(a > bb):
        raise InputError("need 0 <= region area <= bounding-box area > 0 for eq. 18.")
    return np.asarray(np.minimum(1.0, k3 * a / bb))


@dataclass(frozen=True, eq=False)
class Regions:
    """Columnar regions of interest in full-image pixel coordinates.

    Attributes
    ----------
    x, y, w, h : (R,) int -- bounding boxes (left, top, width, height), pixels
    area : (R,) int -- region pixel count A_B
    alpha : (R,) float -- matching level (eq. 18)
    label : (R,) int -- label of the region in :attr:`Segmentation.labels`
    """

    x: NDArray[np.int64]
    y: NDArray[np.int64]
    w: NDArray[np.int64]
    h: NDArray[np.int64]
    area: NDArray[np.int64]
    alpha: FloatArray
    label: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @property
    def boxes(self) -> NDArray[np.int64]:
        """(R, 4) as x, y, w, h."""
        return np.column_stack((self.x, self.y, self.w, self.h)).astype(np.int64)

    @property
    def centre_u(self) -> FloatArray:
        return self.x + (self.w - 1) / 2.0

    def select(self, m: NDArray[np.bool_] | NDArray[np.int64]) -> Regions:
        return Regions(
            self.x[m], self.y[m], self.w[m], self.h[m], self.area[m], self.alpha[m], self.label[m]
        )

    @classmethod
    def from_boxes(cls, boxes: ArrayLike, alpha: ArrayLike | None = None) -> Regions:
        """Regions from (R, 4) boxes x, y, w, h (e.g. a detector's); area = box area."""
        b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        if np.any(b[:, 2:] <= 0) or not np.all(np.isfinite(b)):
            raise InputError("region boxes need finite x, y and positive w, h.")
        bi = np.rint(b).astype(np.int64)
        area = bi[:, 2] * bi[:, 3]
        a = np.ones(len(bi)) if alpha is None else np.asarray(alpha, dtype=np.float64).reshape(-1)
        if a.shape[0] != bi.shape[0]:
            raise InputError(f"{bi.shape[0]} boxes but {a.shape[0]} alpha values.")
        return cls(bi[:, 0], bi[:, 1], bi[:, 2], bi[:, 3], area, a, np.arange(len(bi)))

    @classmethod
    def empty(cls) -> Regions:
        z = np.zeros(0, dtype=np.int64)
        return cls(z, z, z, z, z, np.zeros(0), z)


@dataclass(frozen=True, eq=False)
class Segmentation:
    """Result of :func:`segment_trunks`.

    Attributes
    ----------
    mask : (H, W) bool -- pixels of the kept trunk regions, full image
    labels : (H, W) int32 -- connected-component labels (0 = background), full image
    regions : Regions -- the kept regions with their matching levels
    candidates : Regions -- every labelled region before the "taller than wide" rule
    """

    mask: NDArray[np.bool_]
    labels: NDArray[np.int32]
    regions: Regions
    candidates: Regions


def _fill_holes(binary: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Fill holes: flood the background from the border, invert, OR with the mask."""
    h, w = binary.shape
    pad = np.zeros((h + 2, w + 2), np.uint8)
    pad[1:-1, 1:-1] = binary
    ff = pad.copy()
    mask = np.zeros((h + 4, w + 4), np.uint8)
    cv2.floodFill(ff, mask, (0, 0), 1)
    holes = ff[1:-1, 1:-1] == 0
    return np.asarray(binary | holes.astype(np.uint8))


def label_regions(
    binary: NDArray[np.uint8] | NDArray[np.bool_],
    *,
    min_area: float = 1.0,
    k3: float = 2.0,
    y_offset: int = 0,
) -> tuple[NDArray[np.int32], Regions]:
    """Connected components (8-connected) of a binary mask with their boxes, areas and matching
    levels alpha (Xue 2018 eq. 18); components smaller than ``min_area`` pixels are not returned
    (their pixels keep their label). Box rows are shifted by ``y_offset`` (a cropped image).
    """
    n, lab, stats, _ = cv2.connectedComponentsWithStats(
        np.asarray(binary, dtype=np.uint8), connectivity=8
    )
    st = stats[1:].astype(np.int64)
    ids = np.arange(1, n, dtype=np.int64)
    big = st[:, cv2.CC_STAT_AREA] >= max(1.0, min_area)
    st, ids = st[big], ids[big]
    x, y = st[:, cv2.CC_STAT_LEFT], st[:, cv2.CC_STAT_TOP] + y_offset
    w, h = st[:, cv2.CC_STAT_WIDTH], st[:, cv2.CC_STAT_HEIGHT]
    area = st[:, cv2.CC_STAT_AREA]
    alpha = matching_level(area, w * h, k3) if len(ids) else np.zeros(0)
    return np.asarray(lab, dtype=np.int32), Regions(x, y, w, h, area, alpha, ids)


def segment_trunks(image: ArrayLike, params: SegmentParams | str | None = None) -> Segmentation:
    """Stripping segmentation of trunks (Xue et al. 2018, §2.4.3, Fig. 7; §3.2.2, Fig. 10).

    Steps: crop the canopy rows (Fig. 10b) -> RGB rules to a grey image and its binarisation
    (Fig. 10c-d, :func:`rgb_trunk_mask`) -> fill holes, open, close (Fig. 10e) -> label the
    connected components -> keep the regions whose bounding box is taller than wide (Fig. 10f)
    -> matching level alpha (eq. 18).

    Parameters
    ----------
    image : (H, W, 3) uint8 RGB
    params : SegmentParams or preset name (default "xue2018")

    Returns
    -------
    Segmentation

    Notes
    -----
    The paper's image preprocessing (2D inverse-distance interpolation of "data holes", §2.2)
    is not applied: our inputs have no holes. Vectorised: numpy rules + OpenCV morphology and
    labelling; ~100 images/s at 1280 x 720 on one core (benchmarks/vision_fusion.py).
    """
    p = _params(params)
    img = _check_image(image)
    H, W = img.shape[:2]
    top = round(p.crop_top * H)
    crop = img[top:]
    binary = rgb_trunk_mask(crop, p).astype(np.uint8)
    k = max(1, round(p.kernel * W / 1280.0))
    se = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    binary = _fill_holes(binary)
    binary = np.asarray(cv2.morphologyEx(binary, cv2.MORPH_OPEN, se), dtype=np.uint8)
    binary = np.asarray(cv2.morphologyEx(binary, cv2.MORPH_CLOSE, se), dtype=np.uint8)
    min_area = p.min_area_frac * crop.shape[0] * crop.shape[1]
    lab, cands = label_regions(binary, min_area=min_area, k3=p.k3, y_offset=top)
    n = int(lab.max()) + 1
    w, h = cands.w, cands.h
    keep = h > w if p.taller_than_wide else np.ones(len(cands), bool)
    regions = cands.select(keep)
    labels = np.zeros((H, W), np.int32)
    labels[top:] = lab
    lut = np.zeros(n, bool)
    lut[regions.label] = True
    mask = lut[labels]
    return Segmentation(mask, labels, regions, cands)


def with_params(base: SegmentParams | str, **changes: object) -> SegmentParams:
    """A copy of a preset with some fields changed (e.g. ``with_params("xue2018", k3=1.5)``)."""
    return replace(_params(base), **changes)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# Evaluation against polygon annotations (YOLO segmentation format)
# ---------------------------------------------------------------------------------------------


def read_yolo_vertices(path: str | Path, width: int, height: int) -> list[NDArray[np.int32]]:
    """The class-0 (trunk) polygons of a YOLO-seg label file (``0 x1 y1 x2 y2 ...``,
    normalised), each as an (n, 2) array of pixel coordinates in a ``width`` x ``height``
    image; lines of other classes are skipped.

    Raises
    ------
    InputError
        Naming the file and line: a class id that is not a whole number, coordinates that are
        not finite numbers in 0..1 (1 % slack for exports that overshoot the border), or an
        odd count or fewer than three vertices. A file whose parse would exceed the read
        budget (``STEMMAP_MAX_READ_GB``) or with a line over 1 MB is refused before it is read.
    """
    from stemmap.io._budget import check_text_budget

    # the text, its lines and one line's tokens at a time: ~3 B a byte, ~100 B a line
    check_text_budget(path, "YOLO label file", per_byte=3.0, per_line=100.0)
    polygons: list[NDArray[np.int32]] = []
    text = Path(path).read_text(encoding="utf-8")
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        try:
            cls = float(parts[0])
            vals = np.array([float(v) for v in parts[1:]])
        except ValueError as exc:
            raise InputError(
                f"{path}:{lineno}: a label line is a class id and polygon coordinates, all "
                f"numbers; got {line[:60]!r}."
            ) from exc
        if not (math.isfinite(cls) and cls.is_integer() and cls >= 0):
            raise InputError(
                f"{path}:{lineno}: the class id must be a whole number >= 0 (0 = trunk), got "
                f"{parts[0]!r}."
            )
        if cls != 0:
            continue
        if vals.size < 6 or vals.size % 2:
            raise InputError(
                f"{path}:{lineno}: a polygon needs an even number (>= 6) of coordinates, "
                f"got {vals.size}."
            )
        bad = vals[~(np.isfinite(vals) & (vals >= -0.01) & (vals <= 1.01))]
        if bad.size:
            raise InputError(
                f"{path}:{lineno}: polygon coordinates are normalised to the image (0..1); got "
                f"{bad[0]:g}."
            )
        polygons.append(np.rint(vals.reshape(-1, 2) * [width, height]).astype(np.int32))
    return polygons


def yolo_trunk_mask(path: str | Path, width: int, height: int) -> NDArray[np.bool_]:
    """One (height, width) trunk mask from a YOLO-seg label file: the union of all its
    class-0 polygons (how ``stemmap segment --train --labels`` reads a ``.txt``: the pixel
    classifier learns trunk / not trunk, so the instances are not kept apart). Overlapping
    polygons and a trunk drawn in several parts give the union, with no holes; the memory is
    one mask whatever the number of polygons."""
    m = np.zeros((height, width), np.uint8)
    for v in read_yolo_vertices(path, width, height):
        cv2.fillPoly(m, [v], 1)  # one polygon per call: several at once fill by even-odd
    return m.astype(bool)


def read_yolo_polygons(path: str | Path, width: int, height: int) -> list[NDArray[np.bool_]]:
    """Rasterise the class-0 polygons of a YOLO-seg label file (``0 x1 y1 x2 y2 ...``,
    normalised) into one (height, width) bool mask per polygon: a line is one trunk
    instance (YOLO's convention; converters join the parts of an occluded object into one
    line), as :func:`evaluate_segmentation` counts trunks. For a single mask of all trunks
    use :func:`yolo_trunk_mask`.

    Raises
    ------
    InputError
        As :func:`read_yolo_vertices`, and when the masks (one byte a pixel each) would
        exceed the read budget (``STEMMAP_MAX_READ_GB``), before they are allocated.
    """
    from stemmap.io._budget import check_read_budget, human_bytes

    polygons = read_yolo_vertices(path, width, height)
    need = len(polygons) * width * height
    check_read_budget(
        need,
        path,
        "YOLO label file",
        f"its {len(polygons):,} trunk polygons need one {width} x {height} mask each, "
        f"{human_bytes(need)}",
    )
    masks: list[NDArray[np.bool_]] = []
    for v in polygons:
        m = np.zeros((height, width), np.uint8)
        cv2.fillPoly(m, [v], 1)
        masks.append(m.astype(bool))
    return masks


def evaluate_segmentation(
    mask: NDArray[np.bool_], trunks: list[NDArray[np.bool_]], *, min_coverage: float = 0.5
) -> dict[str, float]:
    """Mask IoU against the union of the annotated trunks, and per-trunk recall.

    A trunk counts as found when the predicted mask covers at least ``min_coverage`` of its
    pixels (our definition; the papers print none for this dataset).
    """
    gt = np.zeros(mask.shape, bool)
    for t in trunks:
        gt |= t
    union = int((mask | gt).sum())
    iou = float((mask & gt).sum() / union) if union else 1.0
    cov = [float((mask & t).sum() / max(int(t.sum()), 1)) for t in trunks]
    found = sum(c >= min_coverage for c in cov)
    return {
        "iou": iou,
        "n_trunks": float(len(trunks)),
        "n_found": float(found),
        "coverage_mean": float(np.mean(cov)) if cov else math.nan,
    }


def evaluate_mangrove(
    folder: str | Path, params: SegmentParams | str | None = None, *, width: int = 1152
) -> dict[str, float]:
    """Run :func:`segment_trunks` on every photo of the mangrove set (``images/*.jpg`` with
    ``labels/*.txt``), downscaled to ``width`` pixels (INTER_AREA), and score it.

    Returns recall (trunks found / trunks), mean and pooled IoU, images, trunks, and the
    segmentation speed in images/s at that size.
    """
    root = Path(folder)
    images = sorted((root / "images").glob("*.jpg"))
    if not images:
        raise InputError(f"no images/*.jpg under {root}; is this the mangrove dataset folder?")
    ious, n_t, n_f, inter, uni, secs = [], 0, 0, 0, 0, 0.0
    for f in images:
        bgr = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(f"{f}: not a readable image.")
        h = round(bgr.shape[0] * width / bgr.shape[1])
        rgb = np.ascontiguousarray(
            cv2.resize(bgr, (width, h), interpolation=cv2.INTER_AREA)[..., ::-1]
        )
        trunks = read_yolo_polygons(root / "labels" / (f.stem + ".txt"), width, h)
        t0 = time.perf_counter()
        seg = segment_trunks(rgb, params)
        secs += time.perf_counter() - t0
        ev = evaluate_segmentation(seg.mask, trunks)
        ious.append(ev["iou"])
        n_t += int(ev["n_trunks"])
        n_f += int(ev["n_found"])
        gt = np.zeros(seg.mask.shape, bool)
        for t in trunks:
            gt |= t
        inter += int((seg.mask & gt).sum())
        uni += int((seg.mask | gt).sum())
    return {
        "images": float(len(images)),
        "n_trunks": float(n_t),
        "recall": n_f / n_t if n_t else math.nan,
        "mean_iou": float(np.mean(ious)),
        "pooled_iou": inter / uni if uni else math.nan,
        "images_per_s": len(images) / secs if secs > 0 else math.nan,
        "width": float(width),
    }
