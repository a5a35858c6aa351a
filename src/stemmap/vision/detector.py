"""Pluggable trunk detectors that turn an image into boxes (for DAIM and fusion).

* :class:`SegmentationDetector` -- our classical stripping segmentation (no model needed).
* :class:`OnnxDetector` -- a user-supplied ONNX model run with onnxruntime (optional
  dependency: ``pip install stemmap[onnx]``). No weights ship with stemmap and none can be
  downloaded by it: the caller passes a model file.

ONNX model contract
-------------------
Input: one float32 tensor (1, 3, H, W), RGB scaled to [0, 1], the image resized (stretched) to
the model's H x W (read from the model when static, else ``input_size``). Output (first output),
one of:

* ``"xyxys"``: (1, N, 5+) or (N, 5+) rows ``x1, y1, x2, y2, score, ...`` in model pixels;
* ``"yolov8"``: (1, 4 + C, N) columns ``cx, cy, w, h, class scores...`` (Ultralytics export);
  the trunk score is class ``class_id``; boxes are then suppressed by NMS.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray
from stemmap.vision.segment import SegmentParams, segment_trunks

__all__ = [
    "Detections",
    "OnnxDetector",
    "SegmentationDetector",
    "TrunkDetector",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Detections:
    """Boxes (R, 4) as x, y, w, h in image pixels, and scores (R,) in [0, 1]."""

    boxes: FloatArray
    scores: FloatArray
    source: str = ""

    def __post_init__(self) -> None:
        b = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 4)
        s = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        if s.shape[0] != b.shape[0]:
            raise InputError(f"{b.shape[0]} boxes but {s.shape[0]} scores.")
        object.__setattr__(self, "boxes", b)
        object.__setattr__(self, "scores", s)

    def __len__(self) -> int:
        return int(self.boxes.shape[0])


@runtime_checkable
class TrunkDetector(Protocol):
    """Anything with ``detect(image (H, W, 3) uint8 RGB) -> Detections``."""

    def detect(self, image: NDArray[np.uint8]) -> Detections: ...


class SegmentationDetector:
    """Boxes of the stripping segmentation's regions; score = matching level alpha (eq. 18)."""

    def __init__(self, params: SegmentParams | str | None = None) -> None:
        self.params = params

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        seg = segment_trunks(image, self.params)
        r = seg.regions
        return Detections(r.boxes.astype(np.float64), r.alpha, "vision:xue2018-segmentation")


class OnnxDetector:
    """Run a user-supplied ONNX trunk detector with onnxruntime (see the module docstring).

    Parameters
    ----------
    model_path : path to a ``.onnx`` file
    output_format : "xyxys" or "yolov8"
    score_threshold : float -- boxes below are dropped
    nms_iou : float -- IoU threshold of non-maximum suppression ("yolov8" always; "xyxys" too)
    input_size : (H, W) -- used only when the model's input has dynamic spatial dimensions
    class_id : int -- trunk class for "yolov8"

    Raises
    ------
    InputError
        If the file is missing or not a valid ONNX model.
    ConfigError
        If onnxruntime is not installed or an option is invalid.
    """

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        *,
        output_format: Literal["xyxys", "yolov8"] = "xyxys",
        score_threshold: float = 0.25,
        nms_iou: float = 0.5,
        input_size: tuple[int, int] = (640, 640),
        class_id: int = 0,
    ) -> None:
        try:
            import onnxruntime as ort
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ConfigError(
                "OnnxDetector needs onnxruntime; install it with `pip install stemmap[onnx]`."
            ) from exc
        if output_format not in ("xyxys", "yolov8"):
            raise ConfigError(f"output_format must be 'xyxys' or 'yolov8', got {output_format!r}.")
        if not 0.0 <= score_threshold <= 1.0 or not 0.0 < nms_iou <= 1.0:
            raise ConfigError("score_threshold must be in [0, 1] and nms_iou in (0, 1].")
        path = Path(model_path)
        if not path.is_file():
            raise InputError(f"ONNX model file {path} does not exist.")
        try:
            self._session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types
            raise InputError(f"{path} is not a loadable ONNX model: {exc}") from exc
        inp = self._session.get_inputs()[0]
        self._input_name = inp.name
        shape = list(inp.shape)
        if len(shape) != 4:
            raise InputError(f"{path}: model input must be 4-D (1, 3, H, W), got {shape}.")
        h, w = shape[2], shape[3]
        self.input_hw = (
            int(h) if isinstance(h, int) and h > 0 else int(input_size[0]),
            int(w) if isinstance(w, int) and w > 0 else int(input_size[1]),
        )
        self.output_format = output_format
        self.score_threshold = float(score_threshold)
        self.nms_iou = float(nms_iou)
        self.class_id = int(class_id)
        self.path = path

    def _preprocess(self, image: NDArray[np.uint8]) -> NDArray[np.float32]:
        h, w = self.input_hw
        x = cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32) / 255.0
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None])

    def detect(self, image: NDArray[np.uint8]) -> Detections:
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise InputError(f"image must be (H, W, 3) uint8 RGB, got {img.shape} {img.dtype}.")
        out: Any = self._session.run(None, {self._input_name: self._preprocess(img)})[0]
        raw = np.asarray(out, dtype=np.float64)
        H, W = img.shape[:2]
        sy, sx = H / self.input_hw[0], W / self.input_hw[1]
        if self.output_format == "xyxys":
            rows = raw.reshape(-1, raw.shape[-1])
            if rows.shape[1] < 5:
                raise InputError(
                    f"{self.path}: 'xyxys' output needs >= 5 columns, got shape {raw.shape}."
                )
            x1, y1, x2, y2, sc = rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4]
        else:
            a = raw[0] if raw.ndim == 3 else raw
            if a.shape[0] < 5 + self.class_id:
                raise InputError(
                    f"{self.path}: 'yolov8' output needs (1, 4 + C, N), got shape {raw.shape}."
                )
            cx, cy, bw, bh = a[0], a[1], a[2], a[3]
            sc = a[4 + self.class_id]
            x1, y1, x2, y2 = cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2
        keep = (sc >= self.score_threshold) & (x2 > x1) & (y2 > y1)
        boxes = np.column_stack((x1 * sx, y1 * sy, (x2 - x1) * sx, (y2 - y1) * sy))[keep]
        scores = np.clip(sc[keep], 0.0, 1.0)
        if len(scores) > 1:
            sel = cv2.dnn.NMSBoxes(
                boxes.tolist(), scores.tolist(), self.score_threshold, self.nms_iou
            )
            keep_idx = np.asarray(sel, dtype=np.int64).reshape(-1)
            boxes, scores = boxes[keep_idx], scores[keep_idx]
        return Detections(boxes, scores, f"vision:onnx:{self.path.name}")


def boxes_xywh(boxes: ArrayLike) -> FloatArray:
    """Validate (R, 4) x, y, w, h boxes (w, h > 0)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if not np.all(np.isfinite(b)) or np.any(b[:, 2:] <= 0):
        raise InputError("boxes must be finite (x, y, w, h) rows with w, h > 0.")
    return b
