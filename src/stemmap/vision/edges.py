"""Edge-based trunk diameter from an image region with laser range (Öhman et al. 2007, §3).

Pipeline (:func:`measure_diameter`): lens undistortion of the region (when the camera has
distortion coefficients) -> optional homomorphic filtering -> vertical Fourier filtering -> Canny,
with a second pass when too few edges are found (homomorphic on, and Kovesi's phase congruency
from the ``phasepack`` library instead of Canny, as Öhman; or Canny with lower hysteresis) ->
keep near-vertical edge pixels -> project to a 1D column signal -> pick the strongest edge and
pair it with the strongest partner within the laser's width bounds -> refine both by a
distance-dependent weighted average -> pixels to metres with the pinhole model.

The Canny pass is OpenCV's; Fleck's (1992) enhancements to Canny, used by Kovesi's MATLAB code,
are in no maintained Python library we found, so the first pass is plain Canny (documented in
docs/algorithms/vision-fusion.md).
"""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray
from stemmap.vision.camera import CameraModel, RigidTransform, undistort_region

__all__ = [
    "COLOUR_PCA",
    "OHMAN2007",
    "EdgeDiameter",
    "EdgeParams",
    "edge_profile",
    "homomorphic_filter",
    "measure_diameter",
    "phase_congruency_edges",
    "select_edge_pair",
    "vertical_edges",
    "vertical_fourier_filter",
]


@dataclass(frozen=True)
class EdgeParams:
    """Parameters of the edge-based diameter measurement.

    Parameters
    ----------
    homomorphic_first : bool
        Apply homomorphic filtering in the first pass (Öhman default: no).
    hom_sigma : float
        Gaussian cutoff of the homomorphic high-emphasis filter, cycles per image side / 2pi.
    hom_low, hom_high : float
        Gains of low (illumination) and high (reflectance) frequencies.
    vertical_angle_deg : float
        Half-angle of the frequency wedge kept by the vertical Fourier filter (structure within
        this angle of vertical passes).
    canny_low, canny_high : float
        First-pass Canny hysteresis thresholds (on a 0-255 image).
    min_edge_fraction : float
        If fewer than this fraction of ROI pixels are vertical edges, run the second pass.
    second_pass_scales : tuple of float
        Threshold multipliers tried in the second pass (iterated hysteresis, Öhman §3.1).
        Phase congruency tries 1.0 first (its first pass has not run: Canny's has).
    min_strength : float
        An edge must be "more than 5 pixels strong" (Öhman §3.2): column count > 5.
    smooth_near, smooth_far : int
        Weighted-average window (bins) for a very near / far tree (Öhman: 9 near ... 3 far).
    near_range, far_range : float, metres
        Ranges mapped to smooth_near and smooth_far (linear in between).
    colour : "luma" or "pca"
        How an RGB region becomes grey: Rec. 601 luma (Öhman worked on grey images) or, ours,
        the region's first colour principal component (keeps bark/soil contrast when their
        luma is equal).
    weighting : "count" or "magnitude"
        Column signal: edge-pixel count (Öhman) or, ours, the sum of |horizontal gradient| over
        the edge pixels, normalised so a full-height edge of median strength scores its row count
        (the "> 5 pixels strong" rule keeps its meaning).
    strips : int
        Ours: measure in this many horizontal strips and take the median width, which tolerates
        leaning trunks and perspective (Öhman: 1, "assumes the trees are straight").
    second_pass : "phase_congruency" or "canny"
        Detector of the second (low-contrast) pass: Kovesi's phase congruency (Öhman §3.1,
        through ``phasepack``) or Canny with the thresholds scaled by ``second_pass_scales``.
    pc_low, pc_high : float in (0, 1)
        Hysteresis thresholds on the phase-congruency edge strength (Kovesi's maximum moment,
        0..1), scaled by ``second_pass_scales`` like the Canny ones. 0.1 / 0.3 are the values
        Kovesi's own examples use with ``hysthresh``.
    pc_scales : int
        Number of log-Gabor scales of the phase congruency (Kovesi's default 4-5; 4 keeps the
        largest filter (3 x 2.1^3 = 28 px wavelength) inside small regions).
    """

    homomorphic_first: bool = False
    hom_sigma: float = 10.0
    hom_low: float = 0.5
    hom_high: float = 1.5
    vertical_angle_deg: float = 20.0
    canny_low: float = 50.0
    canny_high: float = 150.0
    min_edge_fraction: float = 0.01
    second_pass_scales: tuple[float, ...] = (0.6, 0.35, 0.2)
    min_strength: float = 5.0
    smooth_near: int = 9
    smooth_far: int = 3
    near_range: float = 2.0
    far_range: float = 10.0
    colour: str = "luma"
    weighting: str = "count"
    strips: int = 1
    second_pass: str = "phase_congruency"
    pc_low: float = 0.1
    pc_high: float = 0.3
    pc_scales: int = 4

    def __post_init__(self) -> None:
        if not 0 < self.canny_low <= self.canny_high:
            raise ConfigError(
                f"need 0 < canny_low <= canny_high, got {self.canny_low}, {self.canny_high}."
            )
        if not 0 < self.vertical_angle_deg < 90:
            raise ConfigError(
                f"vertical_angle_deg must be in (0, 90), got {self.vertical_angle_deg}."
            )
        if self.smooth_near < 1 or self.smooth_far < 1:
            raise ConfigError("smoothing windows must be >= 1 bin.")
        if not 0 < self.near_range < self.far_range:
            raise ConfigError("need 0 < near_range < far_range (metres).")
        if self.weighting not in ("count", "magnitude"):
            raise ConfigError(f"weighting must be 'count' or 'magnitude', got {self.weighting!r}.")
        if self.strips < 1:
            raise ConfigError(f"strips must be >= 1, got {self.strips}.")
        if self.colour not in ("luma", "pca"):
            raise ConfigError(f"colour must be 'luma' or 'pca', got {self.colour!r}.")
        if self.second_pass not in ("phase_congruency", "canny"):
            raise ConfigError(
                f"second_pass must be 'phase_congruency' or 'canny', got {self.second_pass!r}."
            )
        if not 0 < self.pc_low <= self.pc_high < 1:
            raise ConfigError(f"need 0 < pc_low <= pc_high < 1, got {self.pc_low}, {self.pc_high}.")
        if self.pc_scales < 2:
            raise ConfigError(f"pc_scales must be >= 2, got {self.pc_scales}.")


#: Öhman et al. (2007): Canny, then homomorphic + phase congruency; edges > 5 px strong, 3-9 bin
#: weighted average; other values ours.
OHMAN2007 = EdgeParams()
#: Ours: colour-PCA grey image, gradient-weighted projection, 4 strips (see EdgeParams); the
#: second pass is Canny with lower thresholds (what this preset was measured with).
COLOUR_PCA = EdgeParams(colour="pca", weighting="magnitude", strips=4, second_pass="canny")


def _gray(image: ArrayLike, colour: str = "luma") -> FloatArray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        rgb = img.astype(np.float64)
        if colour == "pca":
            # Project on the first principal component of the region's colours: the grey
            # image with the largest contrast (bark vs soil can be equal in luma).
            flat = rgb.reshape(-1, 3)
            c = flat - flat.mean(axis=0)
            _, _, vt = np.linalg.svd(c[:: max(1, c.shape[0] // 4000)], full_matrices=False)
            img = (c @ vt[0]).reshape(rgb.shape[:2])
        else:
            img = rgb @ np.array([0.299, 0.587, 0.114])
    elif img.ndim != 2:
        raise InputError(f"image must be (H, W) grey or (H, W, 3) RGB, got shape {img.shape}.")
    g = np.asarray(img, dtype=np.float64)
    if g.shape[0] < 3 or g.shape[1] < 3:
        raise InputError(f"image region is too small for edge detection: {g.shape}.")
    return g


def _freq_grid(shape: tuple[int, ...]) -> tuple[FloatArray, FloatArray]:
    fy = np.asarray(np.fft.fftfreq(shape[0])[:, None], dtype=np.float64)
    fx = np.asarray(np.fft.fftfreq(shape[1])[None, :], dtype=np.float64)
    return fx, fy


def homomorphic_filter(
    image: ArrayLike, *, sigma: float = 10.0, low: float = 0.5, high: float = 1.5
) -> FloatArray:
    """Homomorphic filtering (Öhman 2007, §3.1): log -> high-emphasis Gaussian filter -> exp,
    which flattens uneven illumination and boosts reflectance contrast.

    H(f) = low + (high - low) (1 - exp(-|f|^2 / (2 s^2))), s = sigma / image side.

    Returns a float image rescaled to 0-255.
    """
    g = _gray(image)
    lg = np.log1p(g - g.min())  # grey values may be signed (colour PCA): shift to >= 0
    fx, fy = _freq_grid(lg.shape)
    s = sigma / max(lg.shape)
    Hf = low + (high - low) * (1.0 - np.exp(-(fx * fx + fy * fy) / (2 * s * s)))
    out = np.expm1(np.real(np.fft.ifft2(np.fft.fft2(lg) * Hf)))
    lo, hi = float(out.min()), float(out.max())
    return (out - lo) * (255.0 / (hi - lo)) if hi > lo else np.zeros_like(out)


def vertical_fourier_filter(image: ArrayLike, *, angle_deg: float = 20.0) -> FloatArray:
    """Keep near-vertical structure (Öhman 2007, §3.1 "vertical Fourier filtering").

    Vertical edges put their energy near the horizontal frequency axis (f_y ~ 0). The filter
    keeps the wedge |f_y| <= tan(angle) |f_x| (plus the DC term) with a smooth (cosine) roll-off
    of 5 degrees and removes the rest, which suppresses horizontal structure (ground, branches).
    """
    g = _gray(image)
    fx, fy = _freq_grid(g.shape)
    ang = np.degrees(np.arctan2(np.abs(fy), np.abs(fx)))  # 0 = pure horizontal frequency
    roll = 5.0
    w = np.clip((angle_deg + roll - ang) / roll, 0.0, 1.0)
    w = 0.5 - 0.5 * np.cos(np.pi * w)
    w[0, 0] = 1.0
    return np.real(np.fft.ifft2(np.fft.fft2(g) * w))


def _to_u8(g: FloatArray) -> NDArray[np.uint8]:
    lo, hi = float(g.min()), float(g.max())
    if hi <= lo:
        return np.zeros(g.shape, np.uint8)
    return np.asarray(np.clip((g - lo) * (255.0 / (hi - lo)), 0, 255), dtype=np.uint8)


def _phasecong() -> Any:
    """``phasepack.phasecong``, imported on first use (it warns about pyfftw at import)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from phasepack import phasecong
    except ImportError as exc:  # pragma: no cover - phasepack is a dependency
        raise ConfigError(
            "the phase-congruency edge pass needs the 'phasepack' package (a stemmap "
            "dependency): pip install phasepack, or use EdgeParams(second_pass='canny')."
        ) from exc
    return phasecong


def _hysteresis(strength: FloatArray, low: float, high: float) -> NDArray[np.bool_]:
    """Pixels above ``low`` connected (8-neighbourhood) to a pixel above ``high``."""
    weak = strength > low
    lab, n = ndimage.label(weak, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return np.zeros(strength.shape, dtype=bool)
    strong = np.zeros(n + 1, dtype=bool)
    strong[np.unique(lab[strength > high])] = True
    strong[0] = False
    return np.asarray(strong[lab], dtype=bool)


def phase_congruency_edges(
    image: ArrayLike,
    *,
    low: float = 0.1,
    high: float = 0.3,
    n_scales: int = 4,
    max_angle_deg: float = 30.0,
) -> tuple[NDArray[np.bool_], FloatArray]:
    """Near-vertical edges by phase congruency (Kovesi 1999, 2002; Öhman 2007 §3.1).

    Phase congruency is contrast-invariant: a 2-grey-level step between two occluding trunks
    scores like a 100-level one, which is why Öhman uses it for the hard, low-contrast cases.
    The edge strength is Kovesi's maximum moment of the phase-congruency covariance ``M``
    (0..1), computed by ``phasepack.phasecong`` (6 orientations, ``n_scales`` log-Gabor scales,
    smallest wavelength 3 px, scale factor 2.1, noise threshold k = 2: Kovesi's defaults). The
    strength is thinned by non-maximum suppression across the edge -- along image rows, since
    only near-vertical edges are kept -- and linked by hysteresis (``low``, ``high``), as Kovesi's
    ``nonmaxsup`` + ``hysthresh``. Edges whose orientation (phasepack's ``ori``, the direction
    of the feature normal in degrees 0..180) is more than ``max_angle_deg`` from horizontal,
    i.e. edges more than that from vertical, are dropped.

    Parameters
    ----------
    image : (H, W) grey or (H, W, 3) RGB
    low, high : float in (0, 1) -- hysteresis thresholds on ``M``
    n_scales : int, >= 2
    max_angle_deg : float, degrees

    Returns
    -------
    edges : (H, W) bool
    strength : (H, W) float -- ``M``

    References
    ----------
    P. Kovesi, "Image features from phase congruency", Videre 1(3), 1999; "Edges are not just
    steps", ACCV 2002. M. Öhman et al., FSR 2007, §3.1.

    Examples
    --------
    >>> img = np.full((40, 60), 100.0); img[:, 30:] = 103.0  # a 3-level step
    >>> e, m = phase_congruency_edges(img)
    >>> np.flatnonzero(e.any(axis=0)).tolist()  # the step only, not the image borders
    [30]
    """
    g = _gray(image)
    if not 0 < low <= high < 1:
        raise ConfigError(f"need 0 < low <= high < 1, got {low}, {high}.")
    # phasepack filters by FFT (periodic): mirror-pad so the image borders are not edges.
    py, px = min(32, g.shape[0] - 1), min(32, g.shape[1] - 1)
    gp = np.pad(g, ((py, py), (px, px)), mode="reflect")
    M, _, ori, *_ = _phasecong()(
        gp, nscale=int(n_scales), norient=6, minWaveLength=3, mult=2.1, k=2.0
    )
    crop = (slice(py, py + g.shape[0]), slice(px, px + g.shape[1]))
    M = np.nan_to_num(np.asarray(M, dtype=np.float64)[crop])
    o = np.asarray(ori, dtype=np.float64)[crop]
    lft = np.pad(M, ((0, 0), (1, 0)), mode="edge")[:, :-1]
    rgt = np.pad(M, ((0, 0), (0, 1)), mode="edge")[:, 1:]
    thin = np.where(np.greater_equal(M, lft) & np.greater_equal(M, rgt), M, 0.0)
    vertical = (o <= max_angle_deg) | (o >= 180.0 - max_angle_deg)
    return _hysteresis(thin, low, high) & vertical, M


def vertical_edges(
    image: ArrayLike, params: EdgeParams = OHMAN2007, *, return_gradient: bool = False
) -> tuple[NDArray[np.bool_], int] | tuple[NDArray[np.bool_], int, FloatArray]:
    """Near-vertical edge pixels of an image region, with Öhman's two-pass strategy (§3.1).

    Pass 1: Canny on the vertically Fourier-filtered image (homomorphic filtering only with
    ``homomorphic_first``). If it finds fewer than ``min_edge_fraction`` of the pixels, pass 2
    runs on the homomorphically filtered image with ``params.second_pass``: phase congruency
    (:func:`phase_congruency_edges`, Öhman) or Canny, each with its hysteresis thresholds
    scaled by ``second_pass_scales`` in turn until enough edges are found (Öhman: "iterated
    with varying hysteresis threshold values until enough edge features were detected").

    Returns
    -------
    edges : (H, W) bool
    pass_used : int -- 1 (plain Canny) or 2 (homomorphic + second detector)
    gx : (H, W) float, only with ``return_gradient`` -- horizontal Sobel gradient of the
        filtered grey image the edges came from (signed: bright-to-the-right positive)
    """
    p = params
    g = _gray(image, p.colour)

    def run(src: FloatArray, scale: float) -> tuple[NDArray[np.bool_], FloatArray]:
        f = vertical_fourier_filter(src, angle_deg=p.vertical_angle_deg)
        u8 = _to_u8(f)
        e = cv2.Canny(u8, p.canny_low * scale, p.canny_high * scale, L2gradient=True) > 0
        gx = np.asarray(cv2.Sobel(u8, cv2.CV_32F, 1, 0, ksize=3), dtype=np.float64)
        gy = np.asarray(cv2.Sobel(u8, cv2.CV_32F, 0, 1, ksize=3), dtype=np.float64)
        vertical = np.abs(gx) > np.abs(gy) * math.tan(math.radians(60.0))
        return np.asarray(e & vertical), gx

    first = (
        homomorphic_filter(g, sigma=p.hom_sigma, low=p.hom_low, high=p.hom_high)
        if p.homomorphic_first
        else g
    )
    e, gx = run(first, 1.0)
    used = 1
    need = p.min_edge_fraction * e.size
    if e.sum() < need:
        used = 2
        hom = homomorphic_filter(g, sigma=p.hom_sigma, low=p.hom_low, high=p.hom_high)
        pc = p.second_pass == "phase_congruency"
        for sc in (1.0, *p.second_pass_scales) if pc else p.second_pass_scales:
            if pc:
                f = vertical_fourier_filter(hom, angle_deg=p.vertical_angle_deg)
                e, _ = phase_congruency_edges(
                    f, low=p.pc_low * sc, high=p.pc_high * sc, n_scales=p.pc_scales
                )
                gx = np.asarray(cv2.Sobel(_to_u8(f), cv2.CV_32F, 1, 0, ksize=3), np.float64)
            else:
                e, gx = run(hom, sc)
            if e.sum() >= need:
                break
    if return_gradient:
        return e, used, gx
    return e, used


def edge_profile(edges: NDArray[np.bool_], weights: FloatArray | None = None) -> FloatArray:
    """Project edge pixels onto the x axis: the 1D signal of Öhman Fig. 8.

    Without ``weights`` each column counts its edge pixels (Öhman). With ``weights`` (e.g. the
    gradient magnitude, ours) each edge pixel contributes its weight, so a high-contrast
    silhouette outweighs low-contrast bark texture.
    """
    e = np.asarray(edges)
    if e.ndim != 2:
        raise InputError(f"edges must be a 2D mask, got shape {e.shape}.")
    if weights is None:
        return e.sum(axis=0).astype(np.float64)
    return np.asarray(np.where(e, weights, 0.0).sum(axis=0), dtype=np.float64)


@dataclass(frozen=True)
class EdgePair:
    """Two selected edge columns (sub-pixel, after the weighted average) and their strengths."""

    left: float
    right: float
    strength_left: float
    strength_right: float
    ok: bool = True
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok

    @property
    def width_px(self) -> float:
        return self.right - self.left


def select_edge_pair(
    signal: ArrayLike,
    min_px: float,
    max_px: float,
    *,
    min_strength: float = 5.0,
    window: int = 5,
) -> EdgePair:
    """Edge-pair selection of Öhman et al. (2007), §3.2.

    The strongest column is chosen first and matched with the strongest column whose distance
    lies in [min_px, max_px] (the laser's width bounds in pixels), on either side. Both must be
    stronger than ``min_strength``. Each position is then refined by a weighted average of the
    signal over ``window`` bins around it (Öhman: 3 bins far ... 9 bins near).

    Examples
    --------
    >>> s = np.zeros(100); s[20] = 30; s[61] = 12; s[62] = 12; s[90] = 25
    >>> pair = select_edge_pair(s, 30, 50, window=3)
    >>> pair.left, pair.right
    (20.0, 61.5)
    """
    s = np.asarray(signal, dtype=np.float64).reshape(-1)
    n = s.shape[0]
    if not 0 < min_px <= max_px:
        raise ConfigError(f"need 0 < min_px <= max_px, got {min_px}, {max_px}.")
    fail = EdgePair(math.nan, math.nan, math.nan, math.nan, False, "")
    if n == 0 or s.max() <= min_strength:
        return EdgePair(**{**fail.__dict__, "reason": f"no edge stronger than {min_strength} px"})
    i = int(np.argmax(s))
    idx = np.arange(n)
    d = np.abs(idx - i)
    cand = (d >= min_px) & (d <= max_px) & (s > min_strength)
    if not cand.any():
        return EdgePair(
            **{**fail.__dict__, "reason": "no partner edge within the laser's width bounds"}
        )
    j = int(np.argmax(np.where(cand, s, -np.inf)))
    half = max(0, (window - 1) // 2)

    def refine(k: int) -> float:
        lo, hi = max(0, k - half), min(n, k + half + 1)
        w = s[lo:hi]
        return float(np.sum(w * idx[lo:hi]) / np.sum(w)) if w.sum() > 0 else float(k)

    a, b = refine(i), refine(j)
    left, right = (a, b) if a < b else (b, a)
    sl, sr = (s[i], s[j]) if a < b else (s[j], s[i])
    return EdgePair(left, right, float(sl), float(sr))


@dataclass(frozen=True)
class EdgeDiameter:
    """A trunk diameter measured from image edges.

    Attributes
    ----------
    diameter : float, metres (NaN when failed)
    diameter_pinhole : float, metres -- Öhman's pinhole conversion, width_px * range / f
    left_u, right_u : float, columns of the two edges in the ideal pinhole image (the image's
        own columns when the camera has no distortion; see :meth:`CameraModel.undistort_points`)
    pass_used : int
    ok, reason
    """

    diameter: float
    diameter_pinhole: float
    left_u: float
    right_u: float
    pass_used: int
    ok: bool = True
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok


def _smooth_window(range_m: float, p: EdgeParams) -> int:
    t = float(np.clip((range_m - p.near_range) / (p.far_range - p.near_range), 0.0, 1.0))
    w = round(p.smooth_near + t * (p.smooth_far - p.smooth_near))
    return int(w) | 1


def measure_diameter(
    image: ArrayLike,
    box: ArrayLike,
    range_m: float,
    width_bounds: tuple[float, float],
    camera: CameraModel,
    params: EdgeParams = OHMAN2007,
    *,
    laser_to_camera: RigidTransform | None = None,
) -> EdgeDiameter:
    """Trunk diameter from the vertical edges inside ``box`` (Öhman et al. 2007, §3).

    Parameters
    ----------
    image : (H, W, 3) RGB or (H, W) grey
    box : (x, y, w, h) pixels -- the region to search (e.g. a segmented region widened by the
        laser's maximum width, or the projection of the laser cluster)
    range_m : float, metres -- laser range to the trunk's near surface
    width_bounds : (w_min, w_max), metres -- the laser's trunk-width bounds
    camera : CameraModel
        With non-zero distortion coefficients the region is undistorted
        (:func:`~stemmap.vision.camera.undistort_region`) before any edge is measured (Öhman
        §3.2 corrects only the two chosen points; a curved edge would already have blurred the
        1D projection by then).
    laser_to_camera : RigidTransform, optional
        When given, the edge rays are rotated into the laser frame so their horizontal angle is
        exact for a tilted camera (otherwise the camera's own x-z plane is used).

    Returns
    -------
    EdgeDiameter
        ``diameter_pinhole`` = width_px * range / f_x (Öhman). ``diameter`` (ours) converts the
        two edge columns to viewing rays and uses the tangent-line geometry of a cylinder:
        r = R sin(θ/2) with R = range + r the distance to the axis and θ the angle between the
        rays, i.e. r = range s / (1 - s), s = sin(θ/2); this removes the pinhole model's bias
        (it under-estimates by the factor (1 - s) and ignores off-axis foreshortening).
    """
    b = np.asarray(box, dtype=np.float64).reshape(-1)
    if b.shape != (4,) or not np.all(np.isfinite(b)) or b[2] <= 0 or b[3] <= 0:
        raise InputError(f"box must be (x, y, w, h) with w, h > 0, got {b}.")
    if not (range_m > 0 and math.isfinite(range_m)):
        raise InputError(f"range must be a positive number of metres, got {range_m}.")
    img = np.asarray(image)
    H, W = img.shape[:2]
    x0, y0 = max(0, int(b[0])), max(0, int(b[1]))
    x1, y1 = min(W, int(b[0] + b[2])), min(H, int(b[1] + b[3]))
    if x1 - x0 < 3 or y1 - y0 < 3:
        return EdgeDiameter(math.nan, math.nan, math.nan, math.nan, 0, False, "box outside image")
    ox = oy = 0
    if camera.has_distortion:
        # Undistort the region first: a straight trunk edge is curved by the lens, which would
        # smear its column in the 1D projection; from here on pixels are ideal-pinhole pixels.
        img, (ox, oy, w_ud, h_ud) = undistort_region(img, camera, (x0, y0, x1 - x0, y1 - y0))
        x0, y0, x1, y1 = 0, 0, w_ud, h_ud
    f = camera.fx
    w_min, w_max = width_bounds
    lo_px = max(1.0, f * w_min / range_m)
    hi_px = max(1.0, f * w_max / (range_m * 0.9))
    window = _smooth_window(range_m, params)
    bounds = np.linspace(y0, y1, params.strips + 1).round().astype(int)
    lefts, rights, used = [], [], 1
    reason = ""
    for ya, yb in itertools.pairwise(bounds):
        if yb - ya < 3:
            continue
        e, u, gx = vertical_edges(img[ya:yb, x0:x1], params, return_gradient=True)  # type: ignore[misc]
        used = max(used, u)
        if params.weighting == "magnitude":
            mag = np.abs(gx)
            med = float(np.median(mag[e])) if e.any() else 1.0
            sig = edge_profile(e, mag / max(med, 1e-9))
        else:
            sig = edge_profile(e)
        pair = select_edge_pair(sig, lo_px, hi_px, min_strength=params.min_strength, window=window)
        if pair:
            lefts.append(pair.left)
            rights.append(pair.right)
        else:
            reason = pair.reason
    if not lefts:
        return EdgeDiameter(math.nan, math.nan, math.nan, math.nan, used, False, reason)
    widths = np.asarray(rights) - np.asarray(lefts)
    k = int(np.argsort(widths)[len(widths) // 2])
    pair = EdgePair(lefts[k], rights[k], math.nan, math.nan)
    ul, ur = ox + x0 + pair.left, ox + x0 + pair.right
    # The edge at column k of the profile is between pixels k and k+1 of a Canny response; the
    # boundary sits at k + 0.5 on average for a step edge. Width is a difference: unaffected.
    width_px = ur - ul
    d_pin = width_px * range_m / f
    v = oy + y0 + (y1 - y0) / 2.0
    Kinv = np.linalg.inv(camera.K)
    r1 = Kinv @ np.array([ul, v, 1.0])
    r2 = Kinv @ np.array([ur, v, 1.0])
    # Horizontal angle between the rays (trunks are vertical): drop the vertical component.
    if laser_to_camera is not None:
        q1, q2 = laser_to_camera.R.T @ r1, laser_to_camera.R.T @ r2
        a1, a2 = math.atan2(q1[1], q1[0]), math.atan2(q2[1], q2[0])
    else:
        a1, a2 = math.atan2(r1[0], r1[2]), math.atan2(r2[0], r2[2])
    s = math.sin(abs(a2 - a1) / 2.0)
    d_cyl = 2.0 * range_m * s / (1.0 - s) if s < 1 else math.nan
    return EdgeDiameter(d_cyl, d_pin, ul, ur, used)
