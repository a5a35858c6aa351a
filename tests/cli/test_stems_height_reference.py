"""`stemmap stems` states what its heights were measured from (a ground model, or the lowest
stem points of a cloud without ground, with the base's z), and an empty result names the
causes its cloud gives evidence for instead of always pointing at --units / --up-axis
(docs/cli.md, stems)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.cli._stems_base import base_warning
from stemmap.cloud.result import CloudStems
from stemmap.io.clouds import read_cloud

runner = CliRunner()


def _json(tmp_path: Path, cloud: Path) -> dict:
    res = runner.invoke(app, ["stems", str(cloud), "-o", str(tmp_path / "s.csv"), "--json"])
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("rel", ["archi/Tree_1_point_cloud.las", "archi/Tree_2_point_cloud.las"])
def test_tree_without_ground_states_its_base(tmp_path: Path, datasets_dir: Path, rel: str) -> None:
    """The real trees exported without ground: the summary and --json say the heights came
    from the lowest stem points, at the cloud's lowest z (the stem's cut), and no warning:
    one stem is what a segmented tree gives."""
    doc = _json(tmp_path, datasets_dir / rel)
    z0 = float(read_cloud(datasets_dir / rel).xyz[:, 2].min())
    assert doc["n_stems"] == 1
    assert doc["height_reference"] == "lowest stem points"
    assert doc["base_z_m"] == pytest.approx(z0, abs=1e-9)
    assert doc["summary"]["heights from"] == f"lowest stem points, z = {z0:.2f} m"
    res = runner.invoke(app, ["stems", str(datasets_dir / rel), "-o", str(tmp_path / "t.csv")])
    assert "warning" not in res.output


def test_plot_states_its_ground_model(tmp_path: Path, datasets_dir: Path) -> None:
    doc = _json(tmp_path, datasets_dir / "treels" / "pine_plot.laz")
    assert doc["height_reference"] == "ground"
    assert doc["base_z_m"] is None
    assert doc["summary"]["heights from"] == "ground model"


def _pole() -> np.ndarray:
    """A 2 cm pole 2 m tall without ground: too thin to be a stem (below min_diameter)."""
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 2 * np.pi, 4000)
    return np.column_stack((0.01 * np.cos(t), 0.01 * np.sin(t), rng.uniform(0, 2.0, 4000)))


def test_empty_result_gives_the_evidence_not_a_convention_guess(tmp_path: Path) -> None:
    """main warned "pass --units or --up-axis y" on every empty result; a z-up cloud in
    metres (an upright pole) now gets the reason (heights from its lowest points) as the
    warning, and the convention only as a note with the cloud's measured size."""
    path = tmp_path / "pole.xyz"
    np.savetxt(path, _pole(), fmt="%.6f")
    res = runner.invoke(app, ["stems", str(path), "-o", str(tmp_path / "p.csv"), "-q"])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    warned, noted = text.split("note:")
    assert "no ground was found" in warned
    assert "--up-axis" not in warned  # not warned: one possible cause, with the evidence
    assert "0.0 x 0.0 m across and 2.0 m tall (the shape check saw nothing amiss)" in noted


def test_empty_result_of_a_standing_ground_names_the_up_axis(tmp_path: Path) -> None:
    """A bare 20 x 20 m ground written Y up (file (x, z, -y)) read z up: a wall 20 m tall.
    No stems, and the shape check's warning names --up-axis."""
    rng = np.random.default_rng(1)
    n = 40_000
    g = np.column_stack((rng.uniform(0, 20, n), rng.uniform(0, 20, n), rng.normal(0, 0.02, n)))
    path = tmp_path / "wall.xyz"
    np.savetxt(path, np.column_stack((g[:, 0], g[:, 2], -g[:, 1])), fmt="%.6f")
    res = runner.invoke(app, ["stems", str(path), "-o", str(tmp_path / "w.csv")])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "no stems found" in text
    assert "--up-axis y" in text


def _stems(k: int, base: str) -> CloudStems:
    return CloudStems.from_columns(
        xy=np.zeros((k, 2)),
        z=np.ones(k),
        diameter=np.full(k, 0.3),
        n_points=np.full(k, 100),
        base=base,
        base_z=0.5,
    )


def test_several_stems_from_a_stem_base_are_doubted() -> None:
    """The 'no ground' verdict means one tree: two stems from it are a plot whose ground was
    missed (warned); one stem, or stems over a ground model, are not."""
    assert base_warning(_stems(1, "lowest stem points")) is None
    assert base_warning(_stems(3, "ground")) is None
    said = base_warning(_stems(2, "lowest stem points"))
    assert said is not None and "z = 0.50 m" in said and "2 stems" in said
