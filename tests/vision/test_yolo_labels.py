"""YOLO-seg label files: damaged lines are one error naming the file and line.

Before, a class id ``nan`` ended ``stemmap segment --train`` in a ValueError traceback, and
NaN, inf or 1e30 coordinates were cast to garbage pixel coordinates and trained on silently.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from stemmap.errors import InputError
from stemmap.vision.segment import read_yolo_polygons


def test_valid_polygon_and_other_classes(tmp_path: Path) -> None:
    p = tmp_path / "a.txt"
    p.write_text("0 0.1 0.1 0.9 0.1 0.9 0.9 0.1 0.9\n1 0 0 1 0 1 1\n\n0 0 0 1.0 0 1 1\n")
    masks = read_yolo_polygons(p, 40, 30)
    assert len(masks) == 2  # class 1 is not a trunk
    assert masks[0].shape == (30, 40) and 0.55 < masks[0].mean() < 0.75  # 0.8 x 0.8 square


@pytest.mark.parametrize(
    ("line", "what"),
    [
        ("nan 0.1 0.1 0.2 0.1 0.2 0.3", "class id"),
        ("0.5 0.1 0.1 0.2 0.1 0.2 0.3", "class id"),
        ("0 nan 0.1 0.2 0.1 0.2 0.3", "normalised"),
        ("0 0.1 0.1 inf 0.1 0.2 0.3", "normalised"),
        ("0 1e30 0.1 0.2 0.1 0.2 0.3", "normalised"),
        ("0 0.1 0.1 0.2 x 0.2 0.3", "all numbers"),
        ("0 0.1 0.1 0.2 0.1 0.2", "even number"),
    ],
)
def test_damaged_line_names_file_and_line(tmp_path: Path, line: str, what: str) -> None:
    p = tmp_path / "b.txt"
    p.write_text("0 0.1 0.1 0.2 0.1 0.2 0.3\n" + line + "\n")
    with pytest.raises(InputError, match=rf"b\.txt:2: .*{what}"):
        read_yolo_polygons(p, 40, 30)
