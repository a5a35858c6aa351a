"""A real Dask cluster on 127.0.0.1: `dask scheduler` + two `dask worker` processes; one
worker is killed mid-run and the catalog still completes, no chunk lost or doubled, with the
stems of one process over the whole cloud."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from stemmap.cloud import StemConfig, detect_stems

SRC = str(Path(__file__).resolve().parents[2] / "src")
START_TIMEOUT = 60.0  # s, scheduler and workers up (a loaded machine is slow to import)
RUN_TIMEOUT = 240.0  # s, the whole catalog


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    env["DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT"] = "20s"
    return env


def _wait_for(cond, timeout: float, what: str) -> None:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.2)


def _n_workers(sched_file: Path) -> int:
    from distributed import Client

    with Client(scheduler_file=str(sched_file), timeout="20s") as c:
        return len(c.scheduler_info(n_workers=-1)["workers"])


@pytest.mark.slow
def test_worker_killed_mid_run(stand_tiles: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    folder, xyz = stand_tiles
    sched_file = tmp_path / "scheduler.json"
    procs: list[subprocess.Popen[bytes]] = []
    logs = [open(tmp_path / f"proc{k}.log", "wb") for k in range(4)]  # noqa: SIM115
    try:
        procs.append(
            subprocess.Popen(
                [
                    *(sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1"),
                    *("--port", "0", "--no-dashboard", "--scheduler-file", str(sched_file)),
                ],
                env=_env(),
                stdout=logs[0],
                stderr=subprocess.STDOUT,
            )
        )
        _wait_for(sched_file.exists, START_TIMEOUT, "the scheduler file")
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for k in (1, 2):
            procs.append(
                subprocess.Popen(
                    [
                        *(sys.executable, "-m", "dask", "worker", "--scheduler-file"),
                        *(str(sched_file), "--host", "127.0.0.1", "--nthreads", "1"),
                        *("--no-nanny", "--no-dashboard", "--name", f"w{k}"),
                        *("--death-timeout", "60"),
                    ],
                    env=_env(),
                    stdout=logs[k],
                    stderr=subprocess.STDOUT,
                )
            )
        _wait_for(lambda: _n_workers(sched_file) == 2, START_TIMEOUT, "two workers")
        out = tmp_path / "stems.csv"
        work = tmp_path / "stems_chunks"
        cli = subprocess.Popen(
            [
                *(sys.executable, "-m", "stemmap", "stems", str(folder), "--out", str(out)),
                *("--scheduler", address, "--chunk-size", "7.5", "--buffer", "4"),
            ],
            env=_env(),
            stdout=logs[3],
            stderr=subprocess.STDOUT,
        )
        procs.append(cli)
        manifest = work / "manifest.jsonl"

        def n_done() -> int:
            return len(manifest.read_text().splitlines()) if manifest.exists() else 0

        _wait_for(lambda: n_done() >= 2 or cli.poll() is not None, RUN_TIMEOUT, "two chunks")
        assert cli.poll() is None, "the run ended before a worker could be killed"
        procs[1].send_signal(signal.SIGKILL)  # worker w1 dies mid-run
        procs[1].wait(timeout=10)
        cli.wait(timeout=RUN_TIMEOUT)
        log = (tmp_path / "proc3.log").read_text(errors="replace")
        assert cli.returncode == 0, log
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        for fh in logs:
            fh.close()
    lines = [json.loads(s) for s in manifest.read_text().splitlines()]
    ids = [r["chunk"] for r in lines]
    assert len(ids) == len(set(ids)) == 16  # 4 x 4 chunks of 7.5 m: none lost, none doubled
    assert all(r["status"] == "done" for r in lines)
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    got = np.array([[float(r["x"]), float(r["y"]), float(r["diameter"])] for r in rows])
    ref = detect_stems(xyz, StemConfig())
    assert len(got) == len(ref) > 0
    d, i = cKDTree(got[:, :2]).query(ref.xy)
    assert np.unique(i).size == len(ref)
    assert d.max() < 0.005  # tolerance: see test_stems_engine.py
    np.testing.assert_allclose(got[i, 2], ref.diameter, atol=0.005)
