"""report.html: self-contained, loads in headless Chromium without console errors, renders a
non-blank page, and shows exactly the numbers of metrics.json."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.viz.report import dbh_histogram_svg, flatten_metrics, format_number

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None and not os.environ.get("CI"),
    reason="headless Chromium not installed (CI installs it: .ci/run)",
)


class _Cells(HTMLParser):
    """data-key -> text of the metric cells; every src/href attribute."""

    def __init__(self) -> None:
        super().__init__()
        self.cells: dict[str, str] = {}
        self.links: list[str] = []
        self._key: str | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        self._key = a.get("data-key")
        self.links += [v for k, v in attrs if k in ("src", "href") and v]

    def handle_data(self, data: str) -> None:
        if self._key is not None:
            self.cells[self._key] = self.cells.get(self._key, "") + data

    def handle_endtag(self, tag: str) -> None:
        self._key = None


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("report") / "m"
    args = ["map", "--sim", "--sim-trees", "40", "--sim-size", "30", "--backend", "ekf"]
    res = CliRunner().invoke(app, [*args, "--no-progress", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


def _chromium(*args: str, user_dir: Path) -> subprocess.CompletedProcess[str]:
    assert CHROMIUM is not None, "CI must install chromium (.ci/run)"
    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        f"--user-data-dir={user_dir}",
        "--enable-logging=stderr",
        "--v=0",
    ]
    return subprocess.run(
        [CHROMIUM, *flags, *args], capture_output=True, text=True, timeout=180, check=False
    )


def test_report_is_self_contained_and_matches_metrics(run_dir: Path) -> None:
    page = (run_dir / "report.html").read_text()
    p = _Cells()
    p.feed(page)
    # nothing is fetched: images are data URIs, no scripts, stylesheets or links elsewhere
    assert p.links and all(x.startswith("data:image/png;base64,") for x in p.links)
    assert "<script" not in page and "@import" not in page
    metrics = json.loads((run_dir / "metrics.json").read_text())
    leaves = dict(flatten_metrics(metrics))
    assert set(p.cells) == set(leaves)
    for k, v in leaves.items():
        if isinstance(v, float):
            assert float(p.cells[k]) == v, k  # repr round-trips float64 exactly
        elif isinstance(v, list):
            assert p.cells[k] == str(v), k
        else:
            assert p.cells[k] == format_number(v), k
    n_trees = sum(1 for _ in (run_dir / "trees.csv").open()) - 1
    assert f"Trees ({n_trees})" in page


@needs_chromium
def test_report_in_headless_chromium(run_dir: Path, tmp_path: Path) -> None:
    url = (run_dir / "report.html").resolve().as_uri()
    dom = _chromium("--dump-dom", url, user_dir=tmp_path / "u1")
    assert dom.returncode == 0, dom.stderr[-2000:]
    # the rendered DOM has the metrics table with the same numbers as metrics.json
    p = _Cells()
    p.feed(dom.stdout)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    n = metrics["n_trees"]
    assert p.cells["n_trees"] == str(n)
    assert float(p.cells["trajectory_rmse_m"]) == metrics["trajectory_rmse_m"]
    # no console errors, no failed loads
    bad = [
        ln
        for ln in dom.stderr.splitlines()
        if re.search(r"CONSOLE.*(error|Uncaught)|Failed to load|net::ERR_", ln, re.I)
    ]
    assert not bad, bad
    shot = tmp_path / "shot.png"
    res = _chromium(
        f"--screenshot={shot}", "--window-size=1200,1600", url, user_dir=tmp_path / "u2"
    )
    assert res.returncode == 0 and shot.is_file(), res.stderr[-2000:]
    import matplotlib.image as mpimg

    img = mpimg.imread(shot)
    assert img.shape[0] >= 1000 and img.shape[1] >= 1000
    # non-blank: the figure and tables give many distinct colours and a real spread
    flat = img[..., :3].reshape(-1, 3)
    assert flat.std() > 0.05
    assert len(np.unique((flat[::50] * 255).astype(np.uint8), axis=0)) > 50


def test_histogram_svg_counts() -> None:
    svg = dbh_histogram_svg(np.array([0.12, 0.13, 0.18, 0.31, np.nan]), bin_cm=5)
    # classes 10-15 (2 trees), 15-20 (1), 20-25 (0), 25-30 (0), 30-35 (1)
    titles = re.findall(r"<title>([^<]*)</title>", svg)
    assert titles == ["10-15 cm: 2", "15-20 cm: 1", "20-25 cm: 0", "25-30 cm: 0", "30-35 cm: 1"]
