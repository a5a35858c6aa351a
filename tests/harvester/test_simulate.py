import itertools
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.harvester.simulate import CaptureNoise, harvester_stand, simulate_capture
from stemmap.sim.forest import Stand


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_loop_converges_on_the_chosen_trunk(seed):
    """The receding-horizon loop ends on the nearest reachable trunk, within the paper's
    15 cm accuracy (Zheng 2012 §4); the budget of 40 cycles is far above the ~4-8 needed."""
    stand = harvester_stand(25, rng=seed)
    res = simulate_capture(stand, rng=seed)
    assert res.success, res.reason
    assert res.final_error < 0.15
    assert res.cycles <= 15
    # the target is the nearest trunk the crane can reach (none of these stands has one nearer
    # than 2 m, the crane reaches ~10 m, and the scanner sees it from the start pose)
    assert res.target_tree >= 0
    # every executed plan stayed within the joint limits (finite-difference check, 2 % slack)
    assert res.max_velocity_ratio <= 1.02
    assert res.max_acceleration_ratio <= 1.02
    # the distance estimate shrinks every cycle while the target is tracked
    d = [c.distance for c in res.log]
    assert all(b < a for a, b in itertools.pairwise(d))


def test_noise_free_loop_is_nearly_exact():
    """With no encoder, tracking or vibration error only the detector's error remains:
    the head ends within 2 cm (1 cm range noise, trunk >= 20 cm seen from a few metres)."""
    stand = Stand([[5.0, 1.0], [3.0, -6.0]], [0.3, 0.25])
    quiet = CaptureNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    res = simulate_capture(stand, noise=quiet, rng=4)
    assert res.success
    assert res.target_tree == 0
    assert res.final_error < 0.02


def test_target_by_bearing_and_empty_stand():
    stand = Stand([[5.0, 2.5], [5.0, -2.5]], [0.3, 0.3])
    res = simulate_capture(stand, mode="bearing", bearing=math.radians(-25), rng=1)
    assert res.success
    assert res.target_tree == 1
    empty = simulate_capture(Stand(np.zeros((0, 2)), np.zeros(0)), rng=1)
    assert not empty.success
    assert "no trunk" in empty.reason


def test_cli_harvest_sim_prints_log_and_writes_png(tmp_path):
    png = tmp_path / "cap.png"
    result = CliRunner().invoke(app, ["harvest-sim", "--seed", "2", "--png", str(png)])
    assert result.exit_code == 0, result.output
    assert "CAPTURED" in result.output
    assert "capture cycles" in result.output
    assert png.stat().st_size > 10_000
    bad = CliRunner().invoke(app, ["harvest-sim", "--target", "tallest"])
    assert bad.exit_code != 0


def test_tilted_scanner_needs_the_imu():
    # Scanner on a crane tilted 8 deg in roll and 12 deg in pitch (machine on a slope): with the
    # AHRS reading (0.2 deg error) the first scan places the target within 3 cm of the true
    # axis (measured 0.9-2.4 cm, seeds 0-3; a level scan gives the same); without it, the
    # tilted ranges put it 5-10 cm off. The loop re-scans as it approaches, so both capture.
    from stemmap.harvester.capture import ScannerMount

    mount = ScannerMount(roll=math.radians(8.0), pitch=math.radians(12.0))
    for seed in range(3):
        stand = harvester_stand(rng=seed)
        errs = {}
        for imu in (True, False):
            res = simulate_capture(stand, mount=mount, use_imu=imu, rng=seed)
            assert res.success, res.reason
            first = np.array(res.log[0].target_xy)
            errs[imu] = float(np.min(np.hypot(*(stand.trees_xy - first).T)))
        assert errs[True] < 0.03
        assert errs[False] > errs[True] + 0.02


def _first_target(output: str) -> np.ndarray:
    """Target x, y of cycle 1 in the printed cycle table."""
    import re

    m = re.search(r"(-?\d+\.\d+), (-?\d+\.\d+)", output)
    assert m, output
    return np.array([float(m.group(1)), float(m.group(2))])


def test_cli_harvest_sim_tilted_scanner_with_and_without_the_imu(tmp_path, monkeypatch):
    """``--roll-deg/--pitch-deg`` tilt the scan plane and ``--imu/--no-imu`` switch the AHRS
    (the loop's behaviour is test_tilted_scanner_needs_the_imu above). Measured, seed 1, tilt
    8 / 12 deg: the first scan's target is 1.4 cm from the level scanner's with the IMU, 4.1 cm
    without it; all three capture."""
    import stemmap.harvester.simulate as hs

    seen = []
    real = hs.simulate_capture

    def spy(*args, **kw):
        seen.append((kw["mount"], kw["use_imu"]))
        return real(*args, **kw)

    monkeypatch.setattr(hs, "simulate_capture", spy)
    runs = {}
    for name, extra in (
        ("level", []),
        ("imu", ["--roll-deg", "8", "--pitch-deg", "12"]),
        ("no_imu", ["--roll-deg", "8", "--pitch-deg", "12", "--no-imu"]),
    ):
        png = tmp_path / f"{name}.png"
        res = CliRunner().invoke(app, ["harvest-sim", "--seed", "1", *extra, "--png", str(png)])
        assert res.exit_code == 0, res.output
        assert "CAPTURED" in res.output
        runs[name] = _first_target(res.output)
    assert [u for _, u in seen] == [True, True, False]
    assert seen[1][0].roll == pytest.approx(math.radians(8.0))
    assert seen[1][0].pitch == pytest.approx(math.radians(12.0))
    d_imu = float(np.hypot(*(runs["imu"] - runs["level"])))
    d_raw = float(np.hypot(*(runs["no_imu"] - runs["level"])))
    assert d_imu < d_raw - 0.015, (d_imu, d_raw)
    bad = CliRunner().invoke(app, ["harvest-sim", "--roll-deg", "45"])
    assert bad.exit_code != 0
