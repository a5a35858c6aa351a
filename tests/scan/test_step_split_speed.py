"""``benchmarks/step_split_speed.py`` compares the default (the step split on since Dec 5) with
the default without the step split -- two different settings, not the default with itself."""

from __future__ import annotations

import json

import pytest

import step_split_speed as ssp  # benchmarks/ is on sys.path (tests/conftest.py)


def test_the_default_is_timed_against_the_default_without_the_step_split(capsys):
    assert ssp.main(["--batch", "400", "--rounds", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    runs = ("no_step_split_compiled", "default_compiled", "default_numpy")
    assert tuple(out["scans_per_cpu_second"]) == runs
    assert out["ratio_to_no_step_split_compiled"]["no_step_split_compiled"] == [1.0]
    assert out["default"]["step_split"] is True and out["no_step_split"]["step_split"] is False
    paths = out["compiled_vs_numpy_on_the_numpy_batch"]
    # two settings: the step split adds detections on this drive (3 345 against 3 289 on the
    # 1 000-scan batch); each setting's two paths agree in number and, but for round-off, value
    n_default, n_plain = paths["default"]["detections"], paths["no_step_split"]["detections"]
    assert n_default[0] == n_default[1] and n_plain[0] == n_plain[1]
    assert n_default[0] > n_plain[0]
    for p in paths.values():
        assert p["centers"] == 0.0 and p["radii"] == 0.0 and p["arc_deg"] < 1e-9


def test_refuses_a_preset_without_the_step_split(monkeypatch):
    monkeypatch.setattr(ssp, "STEP_SPLIT", {"step_split": True, "step_noise_pool": True})
    with pytest.raises(SystemExit, match="no longer has the step split"):
        ssp.main(["--batch", "400", "--rounds", "1"])
