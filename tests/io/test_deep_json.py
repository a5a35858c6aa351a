"""JSON inputs nested deeper than Python's recursion limit are refused by name.

``json.loads`` recurses once per nested array or object and raises RecursionError (not a
JSONDecodeError) at ~1000 levels, so a 100 kB file of ``[`` escaped every reader as a
traceback; the fuzzer's mutations (bit flips, splices) never build such nesting.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from stemmap.errors import InputError

DEEP = "[" * 100_000


def test_trees_geojson(tmp_path: Path) -> None:
    from stemmap.io.maps import read_trees_geojson

    p = tmp_path / "t.geojson"
    p.write_text('{"type": "FeatureCollection", "features": ' + DEEP)
    with pytest.raises(InputError, match="nests arrays or objects too deeply"):
        read_trees_geojson(p)


def test_camera_json(tmp_path: Path) -> None:
    from stemmap.io.camera_frames import read_camera_frames

    (tmp_path / "camera.json").write_text('{"K": ' + DEEP)
    with pytest.raises(InputError, match=r"camera\.json: nests arrays or objects too deeply"):
        read_camera_frames(tmp_path)


def test_calibration_json(tmp_path: Path) -> None:
    from stemmap.cli._vision import read_calibration

    p = tmp_path / "cal.json"
    p.write_text('{"G": ' + DEEP)
    with pytest.raises(InputError, match="nests arrays or objects too deeply"):
        read_calibration(p)
