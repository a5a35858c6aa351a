"""Coordinate quantisation (stemmap.cloud.quantisation; docs/algorithms/cloud.md
"Coordinate quantisation"): a cloud whose coordinates were rounded to a step coarser than
2 cm -- float32 at UTM values, a 0.1 m LAS scale -- is refused with an error saying why and
how to re-export, instead of giving diameters nobody can trust (before: treels pine at a
0.1 m LAS scale gave a 14.1 cm DBH for a 25.5 cm stem, and float32 UTM clouds "no slice fit
passed the quality tests")."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cloud_robustness import write_las, write_ply_float32
from stemmap.cli import app
from stemmap.cloud.quantisation import (
    MAX_COORDINATE_STEP,
    QuantisedCoordinatesError,
    check_coordinate_step,
    coordinate_step,
)
from stemmap.cloud.stems import StemConfig, detect_stems, detect_stems_file
from stemmap.errors import ConfigError, InputError

UTM = np.array([500_000.0, 6_200_000.0, 300.0])


def _tree(seed: int = 0, r: float = 0.15) -> np.ndarray:
    """A vertical trunk of radius ``r`` seen all round (0-3 m, 3 mm noise) on a flat 4 x 4 m
    ground: enough for the detector's slices at every step this module tests."""
    gen = np.random.default_rng(seed)
    n = 6000
    a, z = gen.uniform(0, 2 * np.pi, n), gen.uniform(0.0, 3.0, n)
    rr = r + gen.normal(0, 0.003, n)
    trunk = np.column_stack((rr * np.cos(a), rr * np.sin(a), z))
    g = gen.uniform(-2, 2, (4000, 2))
    ground = np.column_stack((g, gen.normal(0, 0.005, g.shape[0])))
    return np.vstack((trunk, ground))


def test_the_step_of_a_grid_is_its_spacing() -> None:
    gen = np.random.default_rng(1)
    v = gen.uniform(-3, 3, 5000)
    for q in (0.001, 0.01, 0.1):  # a LAS scale; the values near 0 are single per binade
        assert coordinate_step(np.round(v / q) * q) == pytest.approx(q, rel=1e-6)
    # unrounded coordinates: micrometres even for a sparse band
    assert coordinate_step(gen.uniform(0, 10, 300)) < 1e-4
    assert coordinate_step(np.full(10, 2.0)) == np.inf
    assert np.isnan(coordinate_step([1.0]))
    # a float32 grid printed to 1 mm (a text export): 0.031 / 0.032 m differences
    f32 = (gen.uniform(0, 10, 5000) + 500_000).astype(np.float32).astype(np.float64)
    assert coordinate_step(np.round(f32, 3)) == pytest.approx(0.031, abs=1e-6)


def test_float32_steps_at_utm_values() -> None:
    gen = np.random.default_rng(2)
    x = gen.uniform(0, 10, 5000)
    assert coordinate_step((x + 500_000).astype(np.float32)) == 0.03125
    assert coordinate_step((x + 6_200_000).astype(np.float32)) == 0.5
    # straddling 2**22 = 4 194 304 m: half at 0.25 m, half at 0.5 m -- the coarser is reported
    assert coordinate_step((x + 4_194_299).astype(np.float32)) == 0.5
    # near 0 float32 is fine
    assert coordinate_step(x.astype(np.float32)) < 1e-5


def test_float32_utm_cloud_is_refused_with_the_reason() -> None:
    p = _tree()
    base = detect_stems(p)
    assert len(base) == 1 and abs(base.diameter[0] - 0.30) < 0.01
    # the same cloud at UTM coordinates rounded to 1 mm (a LAS at 0.001 m scale): measured
    mm = detect_stems(np.round(p + UTM, 3))
    assert len(mm) == 1 and abs(mm.diameter[0] - base.diameter[0]) < 0.005
    # ... and stored as float32: x steps 3 cm, y 50 cm -- refused, saying why and what to do
    with pytest.raises(QuantisedCoordinatesError) as err:
        detect_stems((p + UTM).astype(np.float32))
    msg = str(err.value)
    assert "quantised" in msg and "0.031" in msg and "one value" in msg
    assert "float64" in msg and "LAS" in msg
    assert err.value.steps == (0.03125, np.inf)  # the trunk (+-15 cm) spans one y value
    assert isinstance(err.value, InputError)


def test_the_bound_and_the_escape() -> None:
    p = _tree(3)
    ok = detect_stems(np.round(p / MAX_COORDINATE_STEP) * MAX_COORDINATE_STEP)
    assert len(ok) == 1  # exactly at the bound: measured
    coarse = np.round(p / 0.03) * 0.03
    with pytest.raises(QuantisedCoordinatesError):
        detect_stems(coarse)
    # None: measured anyway, at the caller's risk
    detect_stems(coarse, StemConfig(max_coordinate_step=None))
    with pytest.raises(ConfigError):
        StemConfig(max_coordinate_step=0.0)
    assert check_coordinate_step(coarse[:, :2], None) == pytest.approx((0.03, 0.03))


@pytest.mark.parametrize(
    ("name", "refused"),
    [("f32_utm.ply", True), ("las_10cm.las", True), ("las_1mm_utm.las", False)],
)
def test_stems_cli_refuses_a_quantised_file(tmp_path: Path, name: str, refused: bool) -> None:
    p = _tree(4)
    f = tmp_path / name
    if name.endswith(".ply"):
        write_ply_float32(f, p + UTM)
    elif name == "las_10cm.las":
        write_las(f, p, 0.1, 1.0)
    else:
        write_las(f, p + UTM, 0.001, 1000.0)
    res = CliRunner().invoke(app, ["stems", str(f), "-o", str(tmp_path / "s.csv"), "--quiet"])
    if refused:
        assert res.exit_code != 0
        assert "quantised" in res.output and name in res.output
        assert not (tmp_path / "s.csv").exists()
    else:
        assert res.exit_code == 0, res.output
        assert len(detect_stems_file(f)) == 1


@pytest.mark.slow
def test_a_real_tree_at_a_coarse_las_scale_is_refused(datasets_dir: Path, tmp_path: Path) -> None:
    """treels pine (a 1 cm LAS scale as shipped) written at 0.1 m: before, a 14.1 cm DBH for
    its 25.5 cm stem, without a word."""
    from stemmap.io.clouds import read_cloud

    xyz = read_cloud(datasets_dir / "treels/pine.laz").xyz
    f = tmp_path / "pine_10cm.las"
    write_las(f, xyz, 0.1, 1.0)
    with pytest.raises(QuantisedCoordinatesError, match=r"pine_10cm\.las"):
        detect_stems_file(f)
    assert coordinate_step(xyz[:, 0]) == pytest.approx(0.01, rel=1e-3)  # shipped: measured
