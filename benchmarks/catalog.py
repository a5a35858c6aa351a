"""Scale-out benchmark: a simulated multi-tile stand on the Dask engine (prints JSON).

The stand: one simulated 40 x 40 m TLS tile (``stemmap.sim``: 9 stations, coarse TLS, 1 mm
LAS grid) repeated over a square grid of tiles, every copy mirrored differently so neighbouring
tiles differ, written tile by tile as LAZ (only one tile is ever in memory) until ``--points``
points are on disk. Then:

* runs with 1 and 2 workers (local cluster, one process each) and two chunk sizes: wall time,
  throughput, points/s per worker end to end from LAZ, peak RSS per worker, machine load;
* identical stems: every run's merged stems against the first run's;
* resume: a CLI run killed (SIGKILL, whole process group) once half of the chunks are done,
  then resumed -- the chunks computed by the resume must be exactly the ones not done before.

Usage::

    python benchmarks/catalog.py --points 100000000 --out /tmp/catalog_bench
    python benchmarks/catalog.py --points 10000000   # quick
    python benchmarks/catalog.py --points 8000000 --repeats 3 --log runs.jsonl

The machine is shared: absolute speeds depend on its load (reported per run as the 1-minute
load average before and after); the 1 vs 2 worker ratio is the meaningful number, measured
``--repeats`` times per chunk size (pairs run in alternating order), reported per pair with its
median and spread. Each run also reports where the workers' time went (``phases``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from _laz_tiles import stand_cloud, write_laz

TILE = 40.0


def make_tiles(folder: Path, points: int, seed: int) -> tuple[int, int]:
    """Write tiles until ``points`` points are on disk; returns (tiles, points)."""
    folder.mkdir(parents=True, exist_ok=True)
    base = stand_cloud(size=TILE, n_trees=40, seed=seed, stations=3)
    n_tiles = max(1, math.ceil(points / len(base)))
    side = math.ceil(math.sqrt(n_tiles))
    written = 0
    for k in range(n_tiles):
        i, j = k % side, k // side
        xyz = base.copy()
        if (i + j) % 2:  # mirror in x
            xyz[:, 0] = TILE - xyz[:, 0]
        if j % 2:  # mirror in y
            xyz[:, 1] = TILE - xyz[:, 1]
        keep = (xyz[:, 0] < TILE) & (xyz[:, 1] < TILE)  # half-open tiles
        xyz = xyz[keep]
        xyz[:, 0] += i * TILE
        xyz[:, 1] += j * TILE
        path = folder / f"tile_{i:03d}_{j:03d}.laz"
        if not path.exists():  # written under a temporary name: an existing tile is complete
            tmp = folder / f".{path.name}.tmp.laz"
            write_laz(tmp, xyz)
            os.replace(tmp, path)
        written += len(xyz)
    return n_tiles, written


def _cpu_s() -> float:
    return time.process_time()


def _peak_rss() -> int:
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def _tree_cpu_s() -> float:
    """User + system CPU seconds of this process and of its reaped children."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + ch.ru_utime + ch.ru_stime


def run_once(tiles: Path, work: Path, workers: int, chunk: float, buffer: float) -> dict[str, Any]:
    from stemmap.cloud import StemConfig
    from stemmap.engine import Catalog, dask_client, run_stems_catalog

    shutil.rmtree(work, ignore_errors=True)
    tree0 = _tree_cpu_s()
    t0 = time.perf_counter()
    with dask_client(workers) as client:  # the CLI's local cluster (`--workers N`)
        startup = time.perf_counter() - t0
        load0 = os.getloadavg()[0]
        t1 = time.perf_counter()
        cat = Catalog.from_inputs([tiles])
        run = run_stems_catalog(
            cat, StemConfig(), work, chunk_size=chunk, buffer=buffer, client=client
        )
        wall = time.perf_counter() - t1
        rss = client.run(_peak_rss)
        cpu = client.run(_cpu_s)  # fresh workers: their whole CPU time is this run's
        load1 = os.getloadavg()[0]
    # this process + every child reaped when the cluster closed (workers, nannies): scheduler,
    # Dask's own work and worker start-up included
    tree_cpu = _tree_cpu_s() - tree0
    assert run.stems is not None and not run.failed, run.failed
    n = cat.n_points
    return {
        "workers": workers,
        "chunk_size_m": chunk,
        "buffer_m": buffer,
        "chunks": len(run.chunks),
        "points": n,
        "stems": len(run.stems),
        "wall_s": round(wall, 2),
        "cluster_startup_s": round(startup, 2),
        "points_per_s": round(n / wall),
        "points_per_s_per_worker": round(n / wall / workers),
        # load-independent: points per CPU-second a worker spent (reading LAZ, staging,
        # detecting); what one worker does end to end on an otherwise idle core
        "points_per_cpu_s_per_worker": round(n / sum(cpu.values())),
        "worker_cpu_s": sorted(round(v, 1) for v in cpu.values()),
        "process_tree_cpu_s": round(tree_cpu, 1),
        "points_per_process_tree_cpu_s": round(n / tree_cpu) if tree_cpu > 0 else None,
        "peak_rss_per_worker_gb": sorted(round(v / 1e9, 3) for v in rss.values()),
        "load_1min_before_after": [round(load0, 2), round(load1, 2)],
        # where the workers' time went: tasks, wall and CPU seconds per phase (stage: LAZ
        # decoding into chunk fragments; pilot: catalog statistics; prepare: ground step;
        # stems: the rest of the detector)
        "phases": {
            k: {
                "tasks": int(v["tasks"]),
                "task_s": round(v["task_s"], 2),
                "cpu_s": round(v["cpu_s"], 2),
            }
            for k, v in run.phases.items()
        },
        "_stems": run.stems,
    }


def compare(a: Any, b: Any) -> dict[str, Any]:
    from scipy.spatial import cKDTree

    if len(a) != len(b):
        return {"same_count": False, "n": [len(a), len(b)]}
    d, i = cKDTree(b.xy).query(a.xy)
    return {
        "same_count": True,
        "one_to_one": bool(np.unique(i).size == len(a)),
        "max_position_diff_mm": round(float(d.max()) * 1000, 4),
        "max_diameter_diff_mm": round(float(np.abs(b.diameter[i] - a.diameter).max()) * 1000, 4),
        "bit_identical": bool(
            np.array_equal(a.xy, b.xy) and np.array_equal(a.diameter, b.diameter)
        ),
    }


def resume_after_kill(tiles: Path, work: Path, chunk: float, buffer: float) -> dict[str, Any]:
    from stemmap.engine import Catalog, Manifest, plan_chunks

    shutil.rmtree(work, ignore_errors=True)
    src = str(Path(__file__).resolve().parents[1] / "src")
    env = dict(os.environ, PYTHONPATH=src + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cat = Catalog.from_inputs([tiles])
    cmd = [
        *(sys.executable, "-m", "stemmap", "stems", str(tiles), "--out", str(work / "s.csv")),
        *("--work", str(work), "--workers", "2", "--chunk-size", str(chunk)),
        *("--buffer", str(buffer)),
    ]
    proc = subprocess.Popen(
        cmd, env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    man = Manifest(work)
    total = len(plan_chunks(cat, chunk, buffer))
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < 3600:
        if len(man.entries()) >= total // 2:
            break
        time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGKILL)  # the CLI and its local cluster's workers
    proc.wait(timeout=30)
    done_before = {c for c, r in man.entries().items() if r["status"] == "done"}
    n_lines = len(man.path.read_text().splitlines())
    # the same command with --resume (same parameters as the killed run, by construction)
    subprocess.run(
        [*cmd, "--resume"],
        env=env,
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        timeout=3600,
    )
    new_lines = [json.loads(x) for x in man.path.read_text().splitlines()[n_lines:]]
    redone = {r["chunk"] for r in new_lines if r["status"] == "done"}
    all_ids = {c.id for c in plan_chunks(cat, chunk, buffer)}
    final = man.entries()
    return {
        "chunks": total,
        "done_before_kill": len(done_before),
        "computed_on_resume": len(redone),
        "redid_only_unfinished": redone == all_ids - done_before,
        "all_done_after_resume": all(final[c]["status"] == "done" for c in all_ids),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=100_000_000)
    ap.add_argument("--out", type=Path, default=Path("/tmp/stemmap_catalog_bench"))
    ap.add_argument("--chunk-sizes", default="20,40")
    ap.add_argument("--buffer", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument(
        "--repeats", type=int, default=1, help="pairs of 2- and 1-worker runs per chunk size"
    )
    ap.add_argument("--no-resume", action="store_true", help="skip the kill-and-resume run")
    ap.add_argument("--keep", action="store_true", help="keep the tiles and work folders")
    ap.add_argument(
        "--log", type=Path, default=None, help="also append each run's JSON here as it ends"
    )
    args = ap.parse_args()
    tiles = args.out / "tiles"  # tiles already there (same --points/--seed) are reused
    t0 = time.perf_counter()
    n_tiles, n_points = make_tiles(tiles, args.points, args.seed)
    gen_s = time.perf_counter() - t0
    sizes = [float(v) for v in args.chunk_sizes.split(",")]
    runs = []

    def note(rec: dict[str, Any]) -> None:
        if args.log is not None:
            with args.log.open("a") as fh:
                fh.write(json.dumps({k: v for k, v in rec.items() if k != "_stems"}) + "\n")

    note({"generated": n_points, "tiles": n_tiles, "generate_s": round(gen_s, 1)})
    for chunk in sizes:
        for rep in range(args.repeats):
            # alternate the order so a load change does not favour one worker count
            for workers in (2, 1) if rep % 2 == 0 else (1, 2):
                runs.append(run_once(tiles, args.out / "work", workers, chunk, args.buffer))
                runs[-1]["repeat"] = rep
                note(runs[-1])
    ref = runs[0]["_stems"]
    for r in runs:
        r["vs_first_run"] = compare(ref, r.pop("_stems"))
    speedup: dict[str, Any] = {}
    for c in sizes:
        ratios = []
        for rep in range(args.repeats):
            wall = {
                r["workers"]: r["wall_s"]
                for r in runs
                if r["chunk_size_m"] == c and r["repeat"] == rep
            }
            ratios.append(round(wall[1] / wall[2], 3))
        speedup[f"chunk_{int(c)}m"] = {
            "each_pair": ratios,
            "median": round(float(np.median(ratios)), 3),
            "spread": [min(ratios), max(ratios)],
        }
    res: dict[str, Any] = {}
    if not args.no_resume:
        res = resume_after_kill(tiles, args.out / "resume", sizes[-1], args.buffer)
        note({"resume_after_kill": res})
    report = {
        "data": f"simulated TLS stand, {n_tiles} LAZ tiles of {TILE:.0f} m, {n_points} points",
        "laz_bytes": sum(p.stat().st_size for p in tiles.glob("*.laz")),
        "generate_s": round(gen_s, 1),
        "cores": os.cpu_count(),
        "runs": runs,
        "speedup_2_vs_1_worker": speedup,
        "resume_after_kill": res,
    }
    print(json.dumps(report, indent=2))
    if not args.keep:
        shutil.rmtree(args.out, ignore_errors=True)


if __name__ == "__main__":
    main()
