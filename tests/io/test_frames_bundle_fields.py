"""Frames bundles whose fields have the wrong dtype or shape: one error naming the field.

The bundle reader is not among the fuzzed readers; the user walk (Dec 4) found a ValueError
traceback for a (4,) camera_K, a (3,) camera_to_body, 2-column points or string points, and
NaN intrinsics, float frame indices (truncated) and float images (cast to black) accepted.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.io.frames import read_frames_npz, write_frames_npz


def _bundle() -> dict[str, Any]:
    rng = np.random.default_rng(0)
    return {
        "times": np.array([0.0, 0.1, 0.2]),
        "points": rng.normal(size=(9, 3)).astype(np.float32),
        "frame_ptr": np.array([0, 3, 6, 9]),
        "images": rng.integers(0, 255, (2, 6, 8, 3), dtype=np.uint8),
        "depths": rng.uniform(1, 5, (2, 6, 8)).astype(np.float32),
        "image_frames": np.array([0, 2]),
        "camera_K": np.array([[5.0, 0, 4], [0, 5.0, 3], [0, 0, 1]]),
        "camera_to_body": np.eye(4),
    }


def test_the_writers_bundle_reads(tmp_path: Path) -> None:
    b = _bundle()
    p = tmp_path / "ok.npz"
    write_frames_npz(
        p,
        b["times"],
        lidar=[b["points"][i : i + 3] for i in (0, 3, 6)],
        images=b["images"],
        depths=b["depths"],
        image_frames=b["image_frames"],
        camera_matrix=b["camera_K"],
        camera_to_body=b["camera_to_body"],
    )
    back = read_frames_npz(p)
    assert back.lidar is not None and len(back.lidar) == 3
    np.savez(tmp_path / "plain.npz", **b)  # the same fields saved by hand
    assert read_frames_npz(tmp_path / "plain.npz").images is not None


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("camera_K", np.ones(4), "'camera_K' must be"),
        ("camera_K", np.full((3, 3), np.nan), "camera_K must be finite"),
        ("camera_to_body", np.ones(3), "'camera_to_body' must be"),
        ("camera_to_body", np.full((4, 4), np.inf), "camera_to_body must be finite"),
        ("points", np.zeros((9, 2)), "'points' must be"),
        ("points", np.array(["a", "b"]), "'points' must be"),
        ("frame_ptr", np.array([0.0, 3.5, 6, 9]), "'frame_ptr' must be"),
        ("image_frames", np.array([0.0, 1.5]), "'image_frames' must be"),
        ("images", np.zeros((2, 6, 8, 3)), "'images' must be"),
    ],
)
def test_bad_field_is_named(tmp_path: Path, field: str, value: Any, match: str) -> None:
    b = _bundle()
    b[field] = value
    p = tmp_path / "bad.npz"
    np.savez(p, **b)
    with pytest.raises(InputError, match=match):
        read_frames_npz(p)
