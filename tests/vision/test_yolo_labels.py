"""YOLO-seg label files: damaged lines are one error naming the file and line.

Before, a class id ``nan`` ended ``stemmap segment --train`` in a ValueError traceback, and
NaN, inf or 1e30 coordinates were cast to garbage pixel coordinates and trained on silently.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
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


# --- one trunk mask per label file (training), one mask per line (evaluation) -------------


def _square(x0: float, y0: float, s: float, cls: int = 0) -> str:
    return f"{cls} {x0} {y0} {x0 + s} {y0} {x0 + s} {y0 + s} {x0} {y0 + s}"


def test_training_mask_is_the_union_of_every_trunk_polygon(tmp_path: Path) -> None:
    # a trunk drawn as two overlapping polygons and a second trunk in two parts (split by a
    # branch), plus a class-1 polygon: the training mask is the union of the class-0 ones,
    # with no hole where they overlap (cv2.fillPoly given several polygons at once would
    # leave one: it fills by the even-odd rule)
    from stemmap.vision.segment_classifier import read_label_mask

    p = tmp_path / "img.txt"
    lines = [
        _square(0.1, 0.1, 0.3),
        _square(0.2, 0.2, 0.3),
        _square(0.6, 0.1, 0.1),
        _square(0.6, 0.5, 0.1),
        _square(0.8, 0.8, 0.15, cls=1),
    ]
    p.write_text("\n".join(lines) + "\n")
    mask = read_label_mask(p, 100, 80)
    per_line = read_yolo_polygons(p, 100, 80)
    assert len(per_line) == 4  # one instance per class-0 line
    assert np.array_equal(mask, np.logical_or.reduce(per_line))
    assert mask[int(0.3 * 80), int(0.3 * 100)]  # inside both overlapping squares
    assert not mask[int(0.87 * 80), int(0.87 * 100)]  # class 1


def test_training_mask_holds_one_mask_not_one_per_polygon(tmp_path: Path) -> None:
    # 400 small trunk polygons on a 1000 x 750 photo: before, one full-size mask per polygon
    # (400 x 0.75 MB of bool, plus a uint8 copy each) was held before the union -- on a 16 Mpx
    # phone photo a 60 kB label file of 1000 lines asked for 16 GB. Now the polygons are
    # filled into one mask: the peak is a few masks' size whatever the number of polygons.
    import tracemalloc

    from stemmap.vision.segment_classifier import read_label_mask

    w, h = 1000, 750
    rng = np.random.default_rng(0)

    def peak_for(n: int) -> int:
        p = tmp_path / f"many{n}.txt"
        p.write_text("\n".join(_square(*rng.uniform(0, 0.9, 2), 0.05) for _ in range(n)) + "\n")
        tracemalloc.start()
        try:
            mask = read_label_mask(p, w, h)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert mask.any()
        return peak

    one, many = peak_for(1), peak_for(400)  # (the text pre-pass's 16 MB block is in both)
    assert many - one < 2 * w * h, f"400 polygons: +{(many - one) / 1e6:.1f} MB over one"


def test_per_line_masks_beyond_the_read_budget_are_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # evaluation keeps one mask per line (a trunk instance); a label file asking for more
    # than the read budget is refused before the masks are allocated, naming the file
    p = tmp_path / "many.txt"
    p.write_text("\n".join(_square(0.1, 0.1, 0.2) for _ in range(100)) + "\n")
    monkeypatch.setenv("STEMMAP_MAX_READ_GB", "0.01")
    with pytest.raises(InputError, match=r"many\.txt.*100 trunk polygons.*STEMMAP_MAX_READ_GB="):
        read_yolo_polygons(p, 1000, 750)  # 100 x 0.75 MB = 75 MB > 10 MB
    assert len(read_yolo_polygons(p, 100, 75)) == 100  # 0.75 MB: within the limit
