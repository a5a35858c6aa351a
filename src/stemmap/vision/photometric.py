"""Camera-like photometric changes of an RGB photo: white balance, exposure, tone curve, hue,
blur and JPEG compression.

These are what another camera, site or light does to the same scene, and they serve two uses:
the robustness benchmark of the trunk segmentation (``benchmarks/segment_robust.py`` applies
each one to a held-out photo) and training-time augmentation of the pixel classifier
(:func:`random_camera`, used by :func:`stemmap.vision.segment_classifier.training_samples`).

White balance and exposure act in linear light: the sRGB encoding is undone (IEC 61966-2-1
transfer function), the channels multiplied and clipped at 1 (sensor saturation), and the result
re-encoded, which is how a camera's white-balance gains and exposure time act on a scene. The
tone change is a power law on the encoded values (out = in^gamma), standing for another camera's
tone curve. The hue rotation turns the HSV hue (Smith 1978) by a fixed angle.

All functions take and return (H, W, 3) uint8 RGB and never modify their input.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError

__all__ = [
    "CameraRanges",
    "blur",
    "exposure",
    "gamma",
    "grey_world",
    "hue_rotate",
    "jpeg",
    "random_camera",
    "white_balance",
]

_CODES = np.arange(256, dtype=np.float64) / 255.0
#: sRGB code value -> linear light (IEC 61966-2-1), 256 entries.
_TO_LINEAR = np.where(_CODES <= 0.04045, _CODES / 12.92, ((_CODES + 0.055) / 1.055) ** 2.4).astype(
    np.float32
)


def _check(rgb: NDArray[np.uint8]) -> NDArray[np.uint8]:
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError(f"image must be (H, W, 3) uint8 RGB, got {img.shape} {img.dtype}.")
    return img


def _encode(lin: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Linear light (clipped to [0, 1]) -> sRGB uint8."""
    x = np.clip(lin, 0.0, 1.0)
    enc = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.asarray(np.rint(enc * 255.0), dtype=np.uint8)


def white_balance(rgb: NDArray[np.uint8], gains: tuple[float, float, float]) -> NDArray[np.uint8]:
    """Multiply the linear-light R, G, B channels by ``gains`` (each > 0), clip, re-encode."""
    g = np.asarray(gains, dtype=np.float32)
    if g.shape != (3,) or not np.all(g > 0):
        raise ConfigError(f"white-balance gains must be 3 positive numbers, got {gains}.")
    return _encode(_TO_LINEAR[_check(rgb)] * g)


def grey_world(rgb: NDArray[np.uint8], *, saturated: int = 250) -> NDArray[np.uint8]:
    """Grey-world white balance (Buchsbaum 1980, J. Franklin Inst. 310(1), 1-26): gains that
    give the three linear-light channels the same mean, their common mean kept, so that a
    camera's white-balance gains (a diagonal map in linear light) are undone up to clipping.

    Pixels with a channel at or above ``saturated`` (clipped highlights: sky, glare) are left
    out of the means; if none remain, all pixels are used. An image whose channel mean is 0 is
    returned unchanged.
    """
    img = _check(rgb)
    lin = _TO_LINEAR[img].reshape(-1, 3)
    ok = img.reshape(-1, 3).max(axis=1) < saturated
    means = (lin[ok] if ok.any() else lin).mean(axis=0, dtype=np.float64)
    if not np.all(means > 0):
        return img.copy()
    gains = means.mean() / means
    return _encode(lin.reshape(img.shape) * gains.astype(np.float32))


def exposure(rgb: NDArray[np.uint8], gain: float) -> NDArray[np.uint8]:
    """Scale the linear light by ``gain`` > 0 (exposure time / ISO), clipping highlights."""
    return white_balance(rgb, (gain, gain, gain))


def gamma(rgb: NDArray[np.uint8], power: float) -> NDArray[np.uint8]:
    """Tone curve out = in^power on the encoded values in [0, 1] (power > 0)."""
    if not power > 0:
        raise ConfigError(f"gamma power must be > 0, got {power}.")
    lut = np.rint(255.0 * _CODES**power).astype(np.uint8)
    return np.asarray(lut[_check(rgb)])


def hue_rotate(rgb: NDArray[np.uint8], degrees: float) -> NDArray[np.uint8]:
    """Rotate the HSV hue by ``degrees`` (saturation and value kept)."""
    f = _check(rgb).astype(np.float32) * np.float32(1.0 / 255.0)
    hsv = np.asarray(cv2.cvtColor(f, cv2.COLOR_RGB2HSV), dtype=np.float32)  # H in [0, 360)
    hsv[..., 0] = np.mod(hsv[..., 0] + np.float32(degrees), 360.0)
    out = np.asarray(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB), dtype=np.float32)
    return np.asarray(np.clip(np.rint(out * 255.0), 0, 255), dtype=np.uint8)


def blur(rgb: NDArray[np.uint8], sigma: float) -> NDArray[np.uint8]:
    """Gaussian blur with standard deviation ``sigma`` pixels (defocus, motion, a softer lens)."""
    if not sigma >= 0:
        raise ConfigError(f"blur sigma must be >= 0 pixels, got {sigma}.")
    img = _check(rgb)
    if sigma == 0:
        return img.copy()
    return np.asarray(
        cv2.GaussianBlur(img, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT),
        dtype=np.uint8,
    )


def jpeg(rgb: NDArray[np.uint8], quality: int) -> NDArray[np.uint8]:
    """Round trip through baseline JPEG at ``quality`` (1-100; OpenCV/libjpeg, 4:2:0 chroma)."""
    if not 1 <= quality <= 100:
        raise ConfigError(f"JPEG quality must be in 1..100, got {quality}.")
    bgr = np.ascontiguousarray(_check(rgb)[..., ::-1])
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    dec = cv2.imdecode(buf, cv2.IMREAD_COLOR) if ok else None
    if dec is None:  # pragma: no cover - OpenCV failure
        raise InputError("JPEG round trip failed in OpenCV.")
    return np.ascontiguousarray(dec[..., ::-1], dtype=np.uint8)


@dataclass(frozen=True)
class CameraRanges:
    """Ranges of the random camera changes drawn by :func:`random_camera`.

    Fixed from what phone and action cameras do, not tuned on any photo: auto white balance
    errs by up to ~30 % between the red and blue gains under daylight, shade and overcast;
    auto exposure by about one stop either way; tone curves differ by gamma 0.6-1.7; blur up
    to 1.5 px at the classifier's working width (384 px, i.e. ~5 px on a 1280 px frame);
    JPEG quality 25-95; hue up to 12 degrees.

    Attributes
    ----------
    wb_gain : float -- R and B gains (relative to G) drawn log-uniformly in [1/wb_gain, wb_gain]
    exposure_gain : float -- linear gain drawn log-uniformly in [1/exposure_gain, exposure_gain]
    gamma_power : float -- tone power drawn log-uniformly in [1/gamma_power, gamma_power]
    hue_degrees : float -- hue rotation uniform in [-hue_degrees, hue_degrees]
    blur_sigma : float -- with probability 1/2, Gaussian blur with sigma uniform in (0, blur_sigma]
    jpeg_quality : tuple[int, int] -- with probability 1/2, JPEG at a quality uniform in the range
    """

    wb_gain: float = 1.3
    exposure_gain: float = 2.0
    gamma_power: float = 1.7
    hue_degrees: float = 12.0
    blur_sigma: float = 1.5
    jpeg_quality: tuple[int, int] = (25, 95)

    def __post_init__(self) -> None:
        if min(self.wb_gain, self.exposure_gain, self.gamma_power) < 1.0:
            raise ConfigError("wb_gain, exposure_gain and gamma_power must be >= 1.")
        if self.hue_degrees < 0 or self.blur_sigma < 0:
            raise ConfigError("hue_degrees and blur_sigma must be >= 0.")
        lo, hi = self.jpeg_quality
        if not 1 <= lo <= hi <= 100:
            raise ConfigError(f"jpeg_quality must be 1 <= lo <= hi <= 100, got {(lo, hi)}.")


def _log_uniform(rng: np.random.Generator, r: float) -> float:
    return float(np.exp(rng.uniform(-np.log(r), np.log(r))))


def random_camera(
    rgb: NDArray[np.uint8], rng: np.random.Generator, ranges: CameraRanges | None = None
) -> NDArray[np.uint8]:
    """The photo as a random other camera might have taken it: white balance, exposure, tone
    curve, hue rotation, then (each with probability 1/2) blur and JPEG compression, with
    parameters drawn from ``ranges`` (default :class:`CameraRanges`)."""
    r = CameraRanges() if ranges is None else ranges
    gains = (_log_uniform(rng, r.wb_gain), 1.0, _log_uniform(rng, r.wb_gain))
    e = _log_uniform(rng, r.exposure_gain)
    out = white_balance(rgb, (gains[0] * e, e, gains[2] * e))
    out = gamma(out, _log_uniform(rng, r.gamma_power))
    if r.hue_degrees > 0:
        out = hue_rotate(out, float(rng.uniform(-r.hue_degrees, r.hue_degrees)))
    if r.blur_sigma > 0 and rng.random() < 0.5:
        out = blur(out, float(rng.uniform(0.0, r.blur_sigma)) + 1e-3)
    if rng.random() < 0.5:
        out = jpeg(out, int(rng.integers(r.jpeg_quality[0], r.jpeg_quality[1] + 1)))
    return out
