"""CLI: stemmap calibrate | segment | fuse on simulated data."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.fusion.scenes import fusion_scene
from stemmap.io.scans import write_scans_npz
from stemmap.sim.camera import xue2018_rig
from stemmap.types import ScanBatch
from stemmap.vision.camera import apply_homography, laser_plane_homography

RUNNER = CliRunner()
RIG = xue2018_rig()
G = laser_plane_homography(RIG.camera, RIG.laser_to_camera)


def _pairs(path: Path, n: int = 20) -> None:
    rng = np.random.default_rng(0)
    xy = np.column_stack((rng.uniform(2, 7, n), rng.uniform(-1, 1, n)))
    uv = apply_homography(G, xy) + rng.normal(0, 0.5, (n, 2))
    with path.open("w") as fh:
        fh.write("# laser x,y (m), pixel u,v\nx,y,u,v\n")
        for (x, y), (u, v) in zip(xy, uv, strict=True):
            fh.write(f"{x},{y},{u},{v}\n")


def test_calibrate_and_fuse(tmp_path: Path) -> None:
    pairs = tmp_path / "pairs.csv"
    _pairs(pairs)
    calib = tmp_path / "calib.json"
    K = RIG.camera.K
    res = RUNNER.invoke(
        app,
        [
            "calibrate",
            str(pairs),
            "--out",
            str(calib),
            "--method",
            "ransac",
            "--fx",
            str(K[0, 0]),
            "--cx",
            str(K[0, 2]),
            "--cy",
            str(K[1, 2]),
            "--width",
            "1280",
            "--height",
            "720",
            "--pnp",
        ],
    )
    assert res.exit_code == 0, res.output
    doc = json.loads(calib.read_text())
    assert doc["rms_px"] < 1.0  # 0.5 px noise
    assert np.allclose(np.asarray(doc["laser_to_camera"]["t"]), RIG.laser_to_camera.t, atol=0.05)

    sc = fusion_scene(2, rig=RIG)
    scan_path = tmp_path / "scan.npz"
    write_scans_npz(scan_path, ScanBatch.from_scans([sc.scan]))
    img = tmp_path / "frame.png"
    cv2.imwrite(str(img), sc.image[..., ::-1])
    for method in ("xue2018", "ours"):
        out = tmp_path / f"decisions_{method}.csv"
        res = RUNNER.invoke(
            app,
            [
                "fuse",
                "--scan",
                str(scan_path),
                "--image",
                str(img),
                "--calibration",
                str(calib),
                "--out",
                str(out),
                "--method",
                method,
                "--bpa",
                "forest",
            ],
        )
        assert res.exit_code == 0, res.output
        rows = list(csv.DictReader(out.open()))
        assert rows and {"kind", "is_trunk", "mT"} <= set(rows[0])
        assert sum(int(r["is_trunk"]) for r in rows) >= 1


def test_segment(tmp_path: Path) -> None:
    sc = fusion_scene(0, rig=RIG)
    img = tmp_path / "frame.png"
    cv2.imwrite(str(img), sc.image[..., ::-1])
    mask, rois = tmp_path / "mask.png", tmp_path / "rois.csv"
    res = RUNNER.invoke(
        app,
        ["segment", str(img), "--out", str(mask), "--rois", str(rois), "--method", "xue2018"],
    )
    assert res.exit_code == 0, res.output
    m = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE)
    assert m.shape == (720, 1280) and set(np.unique(m)) <= {0, 255}
    rows = list(csv.DictReader(rois.open()))
    assert rows and set(rows[0]) == {"x", "y", "w", "h", "alpha"}


def test_cli_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,u\n1,2,3\n")
    res = RUNNER.invoke(app, ["calibrate", str(bad), "--out", str(tmp_path / "c.json")])
    assert res.exit_code == 2 and "lacks column" in " ".join(res.output.split())
    res = RUNNER.invoke(
        app, ["segment", str(tmp_path / "none.png"), "--out", str(tmp_path / "m.png")]
    )
    assert res.exit_code == 2 and "does not" in " ".join(res.output.split())
    few = tmp_path / "few.csv"
    few.write_text("x,y,u,v\n1,0,1,1\n2,0,2,2\n3,0,3,3\n")
    res = RUNNER.invoke(app, ["calibrate", str(few), "--out", str(tmp_path / "c.json")])
    assert res.exit_code == 2 and "failed" in " ".join(res.output.split())


def _fuse_inputs(tmp_path: Path, empty: bool = False) -> list[str]:
    sc = fusion_scene(2, rig=RIG)
    b = ScanBatch.from_scans([sc.scan])
    if empty:  # a scan with no returns at all
        b = ScanBatch(np.full_like(b.ranges, np.inf), b.times, b.angle_min, b.angle_increment)
    write_scans_npz(tmp_path / "scan.npz", b)
    cv2.imwrite(str(tmp_path / "frame.png"), sc.image[..., ::-1])
    return ["fuse", "--scan", str(tmp_path / "scan.npz"), "--image", str(tmp_path / "frame.png")]


def _calib(tmp_path: Path, doc: dict) -> Path:
    p = tmp_path / "calib.json"
    p.write_text(json.dumps(doc))
    return p


def test_fuse_scan_without_returns(tmp_path: Path) -> None:
    """An empty scan fused to work (it raised ValueError): the image's regions are reported."""
    K = RIG.camera.K.tolist()
    calib = _calib(tmp_path, {"G": G.tolist(), "camera": {"K": K, "width": 1280, "height": 720}})
    argv = [*_fuse_inputs(tmp_path, empty=True), "--calibration", str(calib)]
    for method in ("xue2018", "ours"):
        out = tmp_path / f"d_{method}.csv"
        res = RUNNER.invoke(app, [*argv, "--out", str(out), "--method", method])
        assert res.exit_code == 0, res.output
        assert "has no returns" in res.output
        rows = list(csv.DictReader(out.open()))
        assert rows and all(r["kind"] == "vision" and r["is_trunk"] == "0" for r in rows)


def test_fuse_calibration_errors_name_the_field(tmp_path: Path) -> None:
    argv = _fuse_inputs(tmp_path)
    K = RIG.camera.K.tolist()
    cases = [
        ({}, "lacks the field 'G'"),
        ({"G": [[0, 0, 0]] * 3}, "'G' is singular"),
        ({"G": [[1, 2], [3, 4]]}, "'G' must be a 3x3 array"),
        ({"G": G.tolist(), "camera": {"width": 1280, "height": 720}}, "'camera.K'"),
        ({"G": G.tolist(), "camera": {"K": K, "height": 720}}, "'camera.width'"),
        ({"G": G.tolist(), "camera": {"K": K, "width": -5, "height": 720}}, "'camera.width'"),
        (
            {"G": G.tolist(), "camera": {"K": K, "width": 9, "height": 9}, "laser_to_camera": {}},
            "'laser_to_camera.R'",
        ),
        ([1, 2, 3], "must hold an object"),
    ]
    for doc, expected in cases:
        calib = _calib(tmp_path, doc)
        res = RUNNER.invoke(
            app, [*argv, "--calibration", str(calib), "--out", str(tmp_path / "d.csv")]
        )
        assert res.exit_code == 2, (doc, res.output)
        errs = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
        assert len(errs) == 1 and expected in errs[0], (doc, res.output)
    (tmp_path / "calib.json").write_text('{"G": [1, 2')
    res = RUNNER.invoke(
        app, [*argv, "--calibration", str(tmp_path / "calib.json"), "--out", "d.csv"]
    )
    assert res.exit_code == 2 and "not valid JSON" in res.output


def test_fuse_refuses_a_truncated_image(tmp_path: Path) -> None:
    """fuse reads its photo like segment does: a PNG cut in half is an error, not a half image."""
    K = RIG.camera.K.tolist()
    calib = _calib(tmp_path, {"G": G.tolist(), "camera": {"K": K, "width": 1280, "height": 720}})
    argv = [*_fuse_inputs(tmp_path), "--calibration", str(calib)]
    png = tmp_path / "frame.png"
    png.write_bytes(png.read_bytes()[: png.stat().st_size // 2])
    out = tmp_path / "d.csv"
    res = RUNNER.invoke(app, [*argv, "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert "error:" in res.output and "frame.png" in res.output
    assert not out.exists()


def test_fuse_refuses_an_image_of_another_size_than_the_calibration(tmp_path: Path) -> None:
    """The user walk (Dec 4): a 4608 x 3456 photo fused with a 1280 x 720 calibration ran to
    "0 pair(s): 0 trunk(s)" without a word; G and K hold only at the calibrated size."""
    K = RIG.camera.K.tolist()
    argv = _fuse_inputs(tmp_path)
    h, w = cv2.imread(str(tmp_path / "frame.png")).shape[:2]
    calib = _calib(tmp_path, {"G": G.tolist(), "camera": {"K": K, "width": 2 * w, "height": h}})
    for method in ("xue2018", "ours"):
        out = tmp_path / "d.csv"
        res = RUNNER.invoke(
            app, [*argv, "--calibration", str(calib), "--out", str(out), "--method", method]
        )
        text = " ".join(res.output.split())
        assert res.exit_code == 2, res.output
        assert f"is {w} x {h} pixels but the calibration" in text and f"{2 * w} x {h}" in text
        assert not out.exists()
