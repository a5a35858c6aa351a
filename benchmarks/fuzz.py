"""Fuzz campaign of every file reader: mutated seed files, 0 tracebacks allowed.

Each reader of :data:`stemmap.io.fuzzing.TARGETS` (scan NPZ/CSV, observations/trees CSV,
GeoJSON, trajectories CSV/TUM, LAS, PLY ascii/binary, PCD ascii/binary, XYZ, ROS1 bag, ROS2
sqlite3/mcap, calibration JSON, correspondence CSV, PNG/JPEG through ``stemmap segment``) gets
``--per-target`` inputs made by 1-4 random mutations (bit flips, byte sets, truncation,
deletions, splices, insertions, integer/float header fields set to extreme values, numeric
text tokens replaced) of one valid seed file. An input passes when the reader returns data or
raises a StemmapError (the CLI's one-line ``error:``); any other exception, a hang
(> ``--timeout`` s) or a crash of the process (signal) is a failure.

Inputs run in worker subprocesses limited to ``--max-memory-gb`` of address space, so a crash
or an allocation bomb is recorded instead of stopping the campaign.

Usage::

    python benchmarks/fuzz.py --per-target 5000 --out fuzz.json   # >= 100,000 inputs
    python benchmarks/fuzz.py --per-target 200 --targets las ply_binary

Prints (and writes with --out) JSON: inputs tried per target, failures with the mutation list,
the exception's last line and the input's SHA-256, and the wall time.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def _ops(rng: np.random.Generator) -> list[tuple[int, float, int]]:
    from stemmap.io.fuzzing import MUTATION_KINDS

    n = int(rng.integers(1, 5))
    return [
        (int(rng.integers(len(MUTATION_KINDS))), float(rng.random()), int(rng.integers(1 << 16)))
        for _ in range(n)
    ]


def _worker(target: str, seed: int, start: int, count: int, progress: Path, timeout: float) -> None:
    """Run inputs start..start+count-1 of (target, seed); one JSON line per failure on stdout."""
    import hashlib

    from stemmap.io.fuzzing import check_input, mutate, write_seeds

    logging.disable(logging.CRITICAL)
    warnings.simplefilter("ignore")
    work = Path(tempfile.mkdtemp(prefix="stemmap-fuzz-"))
    base = write_seeds(work, [target])[target]

    def alarm(signum: int, frame: object) -> None:
        raise TimeoutError(f"reader took more than {timeout} s")

    check_input(target, base, work)  # warm-up (imports, JIT) outside the per-input time limit
    signal.signal(signal.SIGALRM, alarm)
    for i in range(start, start + count):
        rng = np.random.default_rng([seed, i])
        ops = _ops(rng)
        data = mutate(base, ops)
        progress.write_text(str(i))
        signal.setitimer(signal.ITIMER_REAL, timeout)
        try:
            tb = check_input(target, data, work)
        except TimeoutError as exc:
            tb = f"hang: {exc}"
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        if tb:
            last = tb.strip().splitlines()[-1]
            rec = {
                "target": target,
                "index": i,
                "ops": ops,
                "error": last[:300],
                "sha256": hashlib.sha256(data).hexdigest(),
            }
            print(json.dumps(rec), flush=True)
    progress.write_text(str(start + count))


def _campaign(args: argparse.Namespace) -> dict[str, object]:
    from stemmap.io.fuzzing import TARGETS

    targets = args.targets or list(TARGETS)
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[1] / "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    report: dict[str, object] = {"per_target": {}, "failures": []}
    failures: list[dict[str, object]] = []
    per: dict[str, dict[str, float]] = {}
    t_all = time.perf_counter()
    for target in targets:
        n = args.per_target // 20 if target.startswith("image_") else args.per_target
        t0 = time.perf_counter()
        done = 0
        crashes = 0
        with tempfile.TemporaryDirectory() as d:
            progress = Path(d) / "progress"
            while done < n:
                progress.write_text(str(done))
                cmd = [
                    sys.executable,
                    __file__,
                    "--worker",
                    target,
                    str(args.seed),
                    str(done),
                    str(n - done),
                    str(progress),
                    str(args.timeout),
                    str(args.max_memory_gb),
                ]
                p = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
                for line in p.stdout.splitlines():
                    if line.startswith("{"):
                        failures.append(json.loads(line))
                last = int(progress.read_text() or done)
                if p.returncode == 0:
                    done = n
                    continue
                crashes += 1
                failures.append(
                    {
                        "target": target,
                        "index": last,
                        "error": f"worker died (exit {p.returncode}): {p.stderr[-300:]}",
                    }
                )
                done = last + 1
        per[target] = {
            "inputs": n,
            "failures": sum(1 for f in failures if f["target"] == target),
            "crashes": crashes,
            "seconds": round(time.perf_counter() - t0, 2),
        }
        print(json.dumps({target: per[target]}), file=sys.stderr, flush=True)
    report["per_target"] = per
    report["inputs_total"] = sum(int(v["inputs"]) for v in per.values())
    report["failures_total"] = len(failures)
    report["failures"] = failures[:500]
    report["seed"] = args.seed
    report["wall_s"] = round(time.perf_counter() - t_all, 1)
    report["note"] = "wall times on a shared, loaded 2-core machine"
    return report


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        import resource

        target, seed, start, count, progress, timeout, mem = sys.argv[2:9]
        lim = int(float(mem) * (1 << 30))
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
        _worker(target, int(seed), int(start), int(count), Path(progress), float(timeout))
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-target", type=int, default=5000, help="inputs per reader")
    ap.add_argument("--targets", nargs="*", help="subset of readers (default: all)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds per input")
    ap.add_argument("--max-memory-gb", type=float, default=4.0, help="address space per worker")
    ap.add_argument("--out", type=Path, help="also write the JSON report here")
    args = ap.parse_args()
    report = _campaign(args)
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
