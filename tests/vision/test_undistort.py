"""Lens undistortion in the camera model, applied before edge diameters (Öhman 2007 §3.2)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stemmap.cli._vision import read_calibration
from stemmap.errors import InputError
from stemmap.sim.camera import CameraRig, render_scene, xue2018_rig
from stemmap.sim.forest import Stand
from stemmap.types import Pose2
from stemmap.vision.camera import CameraModel, project_points, undistort_image
from stemmap.vision.edges import COLOUR_PCA, measure_diameter

BASE = xue2018_rig(width=640, height=360)
#: barrel distortion of a wide-angle machine-vision lens (k1 -0.30, k2 0.08; ~20 px at the
#: 640 px frame's left and right borders)
DIST = np.array([-0.30, 0.08, 0.001, -0.001, 0.0])
CAM_D = CameraModel(BASE.camera.K, 640, 360, DIST)
RIG_D = CameraRig(CAM_D, BASE.laser_to_camera)


def test_normalised_inverts_projection_to_machine_precision() -> None:
    rng = np.random.default_rng(0)
    uv = np.column_stack((rng.uniform(0, 639, 200), rng.uniform(0, 359, 200)))
    xy = CAM_D.normalised(uv)
    back, front = project_points(np.column_stack((xy, np.ones(len(xy)))), CAM_D)
    assert front.all()
    np.testing.assert_allclose(back, uv, atol=1e-6)
    # without distortion it is K^-1 exactly, and undistort_points is the identity
    np.testing.assert_allclose(BASE.camera.undistort_points(uv), uv, atol=1e-9)
    # with it, corners move by pixels (barrel: outwards once undistorted)
    corner = CAM_D.undistort_points([[0.0, 0.0]])[0]
    assert corner[0] < -5 and corner[1] < -2


def test_undistort_image_matches_the_ideal_pinhole_rendering() -> None:
    # A trunk near the left border, rendered through the distorted lens and through the ideal
    # pinhole camera (same K, same pose; the camera looks 15 deg down, so even the ideal edge
    # leans with perspective). Undistorting the distorted image must put the trunk's edge on
    # the ideal image's column in every row (to a pixel); the raw distorted edge is off by
    # several pixels (barrel: pulled towards the centre).
    stand = Stand(np.array([[4.0, 1.8]]), np.array([0.3]))
    dist = render_scene(stand, Pose2(0, 0, 0), RIG_D, rng=1, pixel_noise=0.0)
    ideal = render_scene(stand, Pose2(0, 0, 0), BASE, rng=1, pixel_noise=0.0)
    ud = undistort_image((dist.truth.label == 0).astype(np.uint8) * 255, CAM_D) > 127
    want = ideal.truth.label == 0
    rows = np.flatnonzero(want.any(axis=1) & ud.any(axis=1) & (dist.truth.label == 0).any(axis=1))
    rows = rows[10:-10]

    def left(mask: np.ndarray) -> np.ndarray:
        return np.array([np.flatnonzero(mask[r])[0] for r in rows], dtype=float)

    assert rows.size > 100
    assert np.max(np.abs(left(ud) - left(want))) <= 1.0
    assert np.max(np.abs(left(dist.truth.label == 0) - left(want))) > 5.0


@pytest.mark.parametrize(
    ("diameter", "xy"), [(0.30, (4.0, 1.8)), (0.25, (5.0, -2.4)), (0.40, (3.0, 1.3))]
)
def test_measure_diameter_undistorts_before_edges(diameter: float, xy: tuple[float, float]) -> None:
    # Trunks in the outer third of a distorted frame: with the distortion coefficients the
    # diameter is within 2 % (measured 0.2-0.7 %); a camera model without them reads the
    # barrel-compressed width and under-estimates by > 10 % (measured 14-17 %).
    sc = render_scene(Stand(np.array([xy]), np.array([diameter])), Pose2(0, 0, 0), RIG_D, rng=3)
    bx = sc.truth.tree_uv_box[0]
    rng_m = float(np.hypot(*xy) - diameter / 2)
    box = (bx[0] - bx[2], bx[1] + bx[3] // 4, 3 * bx[2], bx[3] // 2)
    kw = {"laser_to_camera": BASE.laser_to_camera}
    good = measure_diameter(sc.image, box, rng_m, (0.1, 0.6), CAM_D, COLOUR_PCA, **kw)
    naive = measure_diameter(sc.image, box, rng_m, (0.1, 0.6), BASE.camera, COLOUR_PCA, **kw)
    assert good and naive
    assert abs(good.diameter - diameter) / diameter < 0.02
    assert (diameter - naive.diameter) / diameter > 0.10


def _calib(tmp_path: Path, camera: dict[str, object]) -> Path:
    p = tmp_path / "calib.json"
    G = np.eye(3).tolist()
    p.write_text(json.dumps({"G": G, "camera": camera}), encoding="utf-8")
    return p


def test_calibration_file_carries_distortion(tmp_path: Path) -> None:
    K = BASE.camera.K.tolist()
    doc = read_calibration(_calib(tmp_path, {"K": K, "width": 640, "height": 360,
                                             "dist": [-0.3, 0.08, 0.001, -0.001]}))  # fmt: skip
    cam = CameraModel(*doc["camera"])
    np.testing.assert_allclose(cam.dist, [-0.3, 0.08, 0.001, -0.001, 0.0])
    assert (
        CameraModel(
            *read_calibration(_calib(tmp_path, {"K": K, "width": 640, "height": 360}))["camera"]
        ).has_distortion
        is False
    )
    for bad in ([1.0, 2.0], [0.1, 0.0, 0.0, 0.0, float("nan")], "barrel", [0.0] * 8):
        with pytest.raises(InputError, match=r"camera\.dist"):
            read_calibration(_calib(tmp_path, {"K": K, "width": 640, "height": 360,
                                               "dist": bad}))  # fmt: skip


def test_calibrate_cli_writes_distortion(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from stemmap.cli import app
    from stemmap.vision.camera import apply_homography, laser_plane_homography

    G = laser_plane_homography(BASE.camera, BASE.laser_to_camera)
    rng = np.random.default_rng(0)
    xy = np.column_stack((rng.uniform(2, 7, 20), rng.uniform(-1, 1, 20)))
    uv = apply_homography(G, xy)
    pairs = tmp_path / "pairs.csv"
    rows = "".join(f"{a},{b},{c},{d}\n" for (a, b), (c, d) in zip(xy, uv, strict=True))
    pairs.write_text("x,y,u,v\n" + rows, encoding="utf-8")
    K = BASE.camera.K
    base = ["calibrate", str(pairs), "--out", str(tmp_path / "c.json"), "--fx", str(K[0, 0])]
    base += ["--cx", str(K[0, 2]), "--cy", str(K[1, 2]), "--width", "640", "--height", "360"]
    res = CliRunner().invoke(app, [*base, "--dist=-0.3,0.08,0.001,-0.001"])
    assert res.exit_code == 0, res.output
    cam = CameraModel(*read_calibration(tmp_path / "c.json")["camera"])
    np.testing.assert_allclose(cam.dist, [-0.3, 0.08, 0.001, -0.001, 0.0])
    res = CliRunner().invoke(app, [*base, "--dist", "barrel"])
    assert res.exit_code != 0 and "--dist" in res.output
