"""Frames bundle: 3D lidar frames and / or aligned RGB-D frames of one drive in one NPZ file
(the input of ``stemmap map FRAMES.npz --frontend eb-lidar|daim|ours``).

Keys (all optional except ``times``):

* ``times`` (F,) float64, s, strictly increasing -- one per lidar / odometry frame;
* lidar: ``points`` (N, 3) float32, metres, sensor frame (x forward, y left, z up), frame
  ``f`` is ``points[frame_ptr[f]:frame_ptr[f + 1]]``; ``frame_ptr`` (F + 1,) int64;
* RGB-D: ``images`` (C, H, W, 3) uint8 RGB, ``depths`` (C, H, W) float32 z-depth in metres
  (NaN or 0 = no return, aligned pixel for pixel), ``image_frames`` (C,) int64 (the frame each
  image belongs to), ``camera_K`` (3, 3) pinhole intrinsics, ``camera_to_body`` (4, 4) the
  camera -> lidar (vehicle) transform.
"""

from __future__ import annotations

import itertools
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import InputError
from stemmap.io._util import check_npz_sizes
from stemmap.types import FloatArray

__all__ = ["FramesBundle", "is_frames_npz", "read_frames_npz", "write_frames_npz"]


@dataclass(frozen=True, eq=False)
class FramesBundle:
    """A read frames bundle; ``lidar`` / ``images`` are None when the file has none."""

    times: FloatArray
    lidar: tuple[FloatArray, ...] | None
    images: NDArray[np.uint8] | None
    depths: FloatArray | None
    image_frames: NDArray[np.int64] | None
    camera_matrix: FloatArray | None
    camera_to_body: FloatArray | None

    def rig(self) -> object:
        """A :class:`~stemmap.sim.camera.CameraRig` of the bundle's camera (needs RGB-D)."""
        from stemmap.sim.camera import CameraRig
        from stemmap.vision.camera import CameraModel, RigidTransform

        if self.camera_matrix is None or self.camera_to_body is None or self.images is None:
            raise InputError("the frames bundle has no RGB-D camera (camera_K, camera_to_body).")
        h, w = self.images.shape[1:3]
        T = self.camera_to_body
        to_body = RigidTransform(T[:3, :3], T[:3, 3])
        return CameraRig(CameraModel(self.camera_matrix, int(w), int(h)), to_body.inverse())


def write_frames_npz(
    path: Path,
    times: ArrayLike,
    *,
    lidar: Sequence[ArrayLike] | None = None,
    images: Sequence[NDArray[np.uint8]] | None = None,
    depths: Sequence[ArrayLike] | None = None,
    image_frames: ArrayLike | None = None,
    camera_matrix: ArrayLike | None = None,
    camera_to_body: ArrayLike | None = None,
) -> None:
    """Write a frames bundle (see the module docstring); compressed NPZ, atomically."""
    from stemmap.io.atomic import atomic_write

    t = np.asarray(times, dtype=np.float64).reshape(-1)
    out: dict[str, NDArray[np.generic]] = {"times": t}
    if lidar is not None:
        if len(lidar) != t.shape[0]:
            raise InputError(f"{len(lidar)} lidar frames for {t.shape[0]} times.")
        pts = [np.asarray(p, dtype=np.float32).reshape(-1, 3) for p in lidar]
        out["points"] = np.concatenate(pts) if pts else np.zeros((0, 3), np.float32)
        out["frame_ptr"] = np.concatenate(([0], np.cumsum([len(p) for p in pts]))).astype(np.int64)
    if images is not None:
        parts = (depths, image_frames, camera_matrix, camera_to_body)
        if any(x is None for x in parts):
            raise InputError(
                "RGB-D frames need depths, image_frames, camera_matrix and camera_to_body."
            )
        assert depths is not None and image_frames is not None
        out["images"] = np.asarray(images, dtype=np.uint8)
        out["depths"] = np.asarray(depths, dtype=np.float32)
        out["image_frames"] = np.asarray(image_frames, dtype=np.int64).reshape(-1)
        out["camera_K"] = np.asarray(camera_matrix, dtype=np.float64).reshape(3, 3)
        out["camera_to_body"] = np.asarray(camera_to_body, dtype=np.float64).reshape(4, 4)
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(fh, **out)  # type: ignore[arg-type]


def is_frames_npz(path: Path) -> bool:
    """An NPZ holding ``times`` plus lidar (``points``) or RGB-D (``images``) frames."""
    if path.suffix.lower() != ".npz" or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as z:
            return "times" in z.files and ("points" in z.files or "images" in z.files)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return False  # not a bundle: the caller's own reader reports the damage


#: Each bundle field: allowed dtype kinds and the shape rule, checked before any cast (a
#: string or 2-column ``points`` array ended in a ValueError traceback; float frame indices
#: were truncated, float images cast to black).
_FIELDS: dict[str, tuple[str, str]] = {
    "times": ("fiu", "(F,)"),
    "points": ("fiu", "(N, 3)"),
    "frame_ptr": ("iu", "(F + 1,)"),
    "images": ("u", "(C, H, W, 3) uint8"),
    "depths": ("fiu", "(C, H, W)"),
    "image_frames": ("iu", "(C,)"),
    "camera_K": ("fiu", "(3, 3)"),
    "camera_to_body": ("fiu", "(4, 4)"),
}
_SHAPES = {"points": (None, 3), "camera_K": (3, 3), "camera_to_body": (4, 4)}


def _check_fields(z: dict[str, Any], p: Path) -> None:
    """InputError naming the field whose dtype or shape is not what the format says."""
    for key, (kinds, shape) in _FIELDS.items():
        if key not in z:
            continue
        a = z[key]
        ok = a.dtype.kind in kinds and (key != "images" or a.dtype.itemsize == 1)
        want = _SHAPES.get(key)
        if ok and want is not None:
            ok = a.ndim == len(want) and all(
                w is None or n == w for n, w in zip(a.shape, want, strict=True)
            )
        if not ok:
            raise InputError(
                f"frames bundle {str(p)!r}: field {key!r} must be {shape} "
                f"({'whole numbers' if kinds == 'iu' else 'numbers'}), got {a.dtype} {a.shape}; "
                "docs/outputs.md 'Frames bundle'."
            )


def read_frames_npz(path: Path) -> FramesBundle:
    """Read and check a frames bundle.

    Raises
    ------
    InputError
        Missing file or key, inconsistent shapes, non-increasing times, bad frame indices.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"frames bundle {str(p)!r} does not exist.")
    try:
        with np.load(p, allow_pickle=False) as archive:
            check_npz_sizes(archive, p, "frames bundle")
            z = dict(archive)
    except InputError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"frames bundle {str(p)!r} is not a readable NPZ: {exc}") from exc
    if "times" not in z:
        raise InputError(f"frames bundle {str(p)!r} has no 'times' array.")
    _check_fields(z, p)
    t = np.asarray(z["times"], dtype=np.float64).reshape(-1)
    if t.size == 0 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise InputError(f"frames bundle {str(p)!r}: 'times' must be finite and increasing.")
    lidar = None
    if "points" in z:
        ptr = np.asarray(z.get("frame_ptr", np.zeros(0)), dtype=np.int64).reshape(-1)
        pts = np.asarray(z["points"], dtype=np.float64).reshape(-1, 3)
        if ptr.shape[0] != t.shape[0] + 1 or ptr[0] != 0 or ptr[-1] != pts.shape[0]:
            raise InputError(
                f"frames bundle {str(p)!r}: frame_ptr must have {t.shape[0] + 1} entries from 0 "
                f"to the {pts.shape[0]} points."
            )
        if np.any(np.diff(ptr) < 0) or not np.all(np.isfinite(pts)):
            raise InputError(f"frames bundle {str(p)!r}: bad frame_ptr or non-finite points.")
        lidar = tuple(pts[a:b] for a, b in itertools.pairwise(ptr))
    images = depths = frames = K = T = None
    if "images" in z:
        missing = [
            k for k in ("depths", "image_frames", "camera_K", "camera_to_body") if k not in z
        ]
        if missing:
            raise InputError(f"frames bundle {str(p)!r}: RGB-D frames lack {missing}.")
        images = np.asarray(z["images"], dtype=np.uint8)
        depths = np.asarray(z["depths"], dtype=np.float64)
        frames = np.asarray(z["image_frames"], dtype=np.int64).reshape(-1)
        K = np.asarray(z["camera_K"], dtype=np.float64).reshape(3, 3)
        T = np.asarray(z["camera_to_body"], dtype=np.float64).reshape(4, 4)
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(
                f"frames bundle {str(p)!r}: camera_K must be finite with focal lengths > 0."
            )
        if not np.all(np.isfinite(T)):
            raise InputError(f"frames bundle {str(p)!r}: camera_to_body must be finite.")
        if images.ndim != 4 or images.shape[3] != 3 or depths.shape != images.shape[:3]:
            raise InputError(
                f"frames bundle {str(p)!r}: images (C, H, W, 3) and depths (C, H, W) must agree; "
                f"got {images.shape} and {depths.shape}."
            )
        if frames.shape[0] != images.shape[0] or (
            frames.size and (frames.min() < 0 or frames.max() >= t.shape[0])
        ):
            raise InputError(
                f"frames bundle {str(p)!r}: image_frames must give each of the "
                f"{images.shape[0]} images a frame in [0, {t.shape[0]})."
            )
    return FramesBundle(t, lidar, images, depths, frames, K, T)
