"""Multi-scale pixel features for the trainable trunk classifier (ilastik style).

The feature set follows ilastik's pixel-classification defaults (Sommer et al. 2011, "ilastik:
Interactive learning and segmentation toolkit", ISBI; Berg et al. 2019, Nat. Methods 16, §Pixel
Classification): Gaussian-smoothed colour, gradient magnitude, Laplacian of Gaussian,
structure-tensor eigenvalues and Hessian-of-Gaussian eigenvalues at several scales, plus a local
standard deviation (texture). It was fixed before looking at any trunk photo (no feature
selection on the data; see docs/algorithms/vision-fusion.md, "Trainable pixel classifier").

Features are computed at a fixed working width (default 384 px, the image is area-downscaled
first) so that the scales mean the same fraction of the field of view whatever the camera
resolution, and so that a 1280 x 720 frame costs about as much as a 12 Mpx photo.
All operations are OpenCV separable filters on float32 images.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError

__all__ = ["FEATURE_VERSION", "feature_names", "pixel_features", "working_size"]

#: Version of the feature definition; a model stores it and refuses another one.
FEATURE_VERSION = 1

#: Scales (Gaussian sigma, pixels at the working width) of the smoothed colour channels.
COLOUR_SIGMAS = (0.7, 1.6, 3.5, 8.0)
#: Scales of the luminance texture / edge features.
EDGE_SIGMAS = (1.0, 2.0, 4.0, 8.0)
_COLOUR_NAMES = ("R", "G", "B", "L", "a", "b", "S", "exg")


def working_size(width: int, height: int, work_width: int) -> tuple[int, int]:
    """(w, h) of the working image: ``work_width`` wide (never upscaled), same aspect."""
    if width < 1 or height < 1:
        raise InputError(f"image must be at least 1 x 1 pixels, got {width} x {height}.")
    if work_width < 16:
        raise ConfigError(f"work_width must be >= 16 pixels, got {work_width}.")
    w = min(width, work_width)
    h = max(1, round(height * w / width))
    return w, h


def feature_names() -> list[str]:
    """Names of the columns returned by :func:`pixel_features`, in order."""
    names = [f"{c}_s{s}" for s in COLOUR_SIGMAS for c in _COLOUR_NAMES]
    for s in EDGE_SIGMAS:
        names += [f"gradmag_s{s}", f"log_s{s}", f"std_s{s}"]
        names += [f"st_l1_s{s}", f"st_l2_s{s}", f"st_vert_s{s}"]
        names += [f"hess_l1_s{s}", f"hess_l2_s{s}"]
    return names


def _blur_direct(x: NDArray[np.float32], sigma: float) -> NDArray[np.float32]:
    return np.asarray(
        cv2.GaussianBlur(x, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT),
        dtype=np.float32,
    )


def _blur(x: NDArray[np.float32], sigma: float) -> NDArray[np.float32]:
    """Gaussian smoothing; for sigma >= 3 computed on a 2x / 4x area-downscaled copy and
    bilinearly upsampled (a Gaussian pyramid step: the result is smooth at that scale, ~10x
    cheaper). ``x`` has at most 4 channels (OpenCV's fast paths)."""
    h, w = x.shape[:2]
    f = 1 if sigma < 3.0 else (2 if sigma < 6.0 else 4)
    if f == 1 or min(h, w) < 8 * f:
        return _blur_direct(x, sigma)
    small = cv2.resize(x, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
    s = math.sqrt(max(sigma * sigma - 0.25 * f * f, 0.25)) / f
    out = cv2.resize(
        _blur_direct(np.asarray(small, np.float32), s), (w, h), interpolation=cv2.INTER_LINEAR
    )
    return np.asarray(out, dtype=np.float32)


def _colour_channels(rgb: NDArray[np.uint8]) -> list[NDArray[np.float32]]:
    """Three contiguous groups: (R, G, B), (CIE L*, a*, b*), (HSV saturation, excess green
    2G - R - B), all scaled to about [0, 1] (the 8 colour channels, in ``_COLOUR_NAMES`` order)."""
    f = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
    lab = np.asarray(cv2.cvtColor(f, cv2.COLOR_RGB2Lab), dtype=np.float32)
    lab *= np.array([0.01, 1 / 127.0, 1 / 127.0], np.float32)  # L in [0, 100], a, b ~ +-127
    mx = f.max(axis=2)
    mn = f.min(axis=2)
    sat = (mx - mn) / np.maximum(mx, np.float32(1e-6))
    exg = 2.0 * f[..., 1] - f[..., 0] - f[..., 2]
    return [f, lab, np.dstack((sat, exg)).astype(np.float32)]


def _eig2(
    a: NDArray[np.floating], b: NDArray[np.floating], c: NDArray[np.floating]
) -> tuple[NDArray[np.floating], NDArray[np.floating]]:
    """Eigenvalues (larger, smaller) of the symmetric 2x2 matrices [[a, b], [b, c]]."""
    half_tr = 0.5 * (a + c)
    disc = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    return half_tr + disc, half_tr - disc


def pixel_features(rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
    """Per-pixel feature stack of an RGB image at its own resolution.

    Parameters
    ----------
    rgb : (h, w, 3) uint8 RGB, already at the working resolution

    Returns
    -------
    (h, w, F) float32, F = len(feature_names()):

    * the 8 colour channels of ``_colour_channels`` smoothed at each of ``COLOUR_SIGMAS``;
    * on the luminance L, at each of ``EDGE_SIGMAS``: gradient magnitude of the Gaussian
      derivative, Laplacian of Gaussian (sigma^2-normalised), local standard deviation, the
      structure-tensor eigenvalues (derivatives at sigma / 2, integration at sigma) and its
      "verticality" (J_xx - J_yy) / (J_xx + J_yy) (bark edges of upright stems run vertically),
      and the Hessian-of-Gaussian eigenvalues (sigma^2-normalised; ridges and valleys).
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise InputError(f"features need an (h, w, 3) uint8 RGB image, got {rgb.shape}.")
    groups = _colour_channels(rgb)
    h, w = rgb.shape[:2]
    out: list[NDArray[np.floating]] = []
    for s in COLOUR_SIGMAS:
        for grp in groups:
            sm = _blur(grp, s).reshape(h, w, -1)
            out.extend(sm[..., k] for k in range(sm.shape[2]))
    lum = np.ascontiguousarray(groups[1][..., 0])
    for s in EDGE_SIGMAS:
        g = _blur(lum, s)
        gx = np.asarray(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125))
        gy = np.asarray(cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125))
        out.append(np.sqrt(gx * gx + gy * gy) * s)
        gxx = np.asarray(cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3, scale=0.25), np.float32)
        gyy = np.asarray(cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3, scale=0.25), np.float32)
        gxy = np.asarray(cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3, scale=0.25), np.float32)
        out.append((gxx + gyy) * (s * s))
        var = _blur(lum * lum, s) - g * g
        out.append(np.sqrt(np.maximum(var, 0.0)))
        # structure tensor: derivatives at sigma / 2, integrated at sigma
        gi = _blur(lum, max(0.5, s / 2))
        ix = np.asarray(cv2.Sobel(gi, cv2.CV_32F, 1, 0, ksize=3, scale=0.125))
        iy = np.asarray(cv2.Sobel(gi, cv2.CV_32F, 0, 1, ksize=3, scale=0.125))
        jxx, jyy, jxy = _blur(ix * ix, s), _blur(iy * iy, s), _blur(ix * iy, s)
        l1, l2 = _eig2(jxx, jxy, jyy)
        out += [np.sqrt(np.maximum(l1, 0.0)), np.sqrt(np.maximum(l2, 0.0))]
        out.append((jxx - jyy) / (jxx + jyy + 1e-6))
        h1, h2 = _eig2(gxx, gxy, gyy)
        out += [h1 * (s * s), h2 * (s * s)]
    return np.stack(out, axis=-1).astype(np.float32, copy=False)
