"""``stemmap detect`` / ``stemmap map`` over many drive logs: one Dask task per log.

The command's entry calls :func:`wants_logs`; when it is true (several inputs, a folder of
logs, a glob, a list file, ``--workers`` or ``--scheduler``) it hands its parameters to
:func:`run_many_logs`, which expands the logs (:func:`stemmap.engine.logs.expand_logs`) and
runs, per log, **the single-log command itself** in a worker (:func:`run_log_command`) with
``--out`` pointing into ``OUT/<log name>/``: the per-log products are the single-log
command's products (same code, same run_products manifest, all-or-nothing, inputs never
overwritten). A summary table (``OUT/summary.csv``, also printed) lists every log with its
status, time and error; the exit code is 1 if any log failed, after the others finished.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import typer

from stemmap.cli._catalog import EngineOptions, wants_engine
from stemmap.cli._common import fail_on_stemmap_error, out, print_error, progress
from stemmap.cli._validate import bounded
from stemmap.errors import ConfigError

__all__ = [
    "LogError",
    "SchedulerOption",
    "WorkersOption",
    "run_log_command",
    "run_many_logs",
    "wants_logs",
]

WorkersOption = Annotated[
    int | None,
    typer.Option(
        "--workers",
        help="Several logs: worker processes of the local Dask cluster, one log per task "
        "[default: one per core].",
        callback=bounded("--workers", ge=1),
        rich_help_panel="Many logs (Dask engine)",
    ),
]
SchedulerOption = Annotated[
    str | None,
    typer.Option(
        "--scheduler",
        help="Several logs: submit to a running Dask scheduler tcp://HOST:PORT instead (logs "
        "and --out on a file system its workers share).",
        rich_help_panel="Many logs (Dask engine)",
    ),
]

#: Columns of ``summary.csv`` (the command-specific counts may be empty for a failed log).
SUMMARY_COLUMNS = (
    "log",
    "input",
    "status",
    "output",
    "seconds",
    "n_scans",
    "n_observations",
    "n_trees",
    "backend",
    "false_trees_removed",
    "duplicates_1m",
    "associated_fraction",
    "motion_source",
    "distance_m",
    "drift_estimate_percent",
    "error",
)
#: Per command: the parameter holding the inputs and the one holding ``--out``.
_INPUT_PARAM = {"detect": "scans", "map": "logs"}
_OUT_PARAM = {"detect": "out_path", "map": "out_dir"}
#: Per command: options that name one file for one log and cannot be shared by several.
_SINGLE_LOG_OPTIONS = {
    "detect": {},
    "map": {
        "odometry": "--odometry (each log uses its <stem>_odometry.csv)",
        "dataset": "--dataset",
        "sim": "--sim",
        "gnss": "--gnss",
        "imu": "--imu",
        "camera": "--camera",
        "rerun": "--rerun",
    },
}


class LogError(Exception):
    """A log's command ended with an ``error:`` (its message is the error text)."""


def wants_logs(inputs: Sequence[Path] | None, workers: int | None, scheduler: str | None) -> bool:
    """Whether ``stemmap detect`` / ``map`` runs the multi-log runner: several inputs, a
    folder that is not a ROS 2 bag, a glob, a list file of logs, ``--workers`` or
    ``--scheduler``. One log file (or bag folder) alone runs in this process as before."""
    from stemmap.engine.logs import LOG_EXTENSIONS

    if not inputs:
        return workers is not None or scheduler is not None
    opts = EngineOptions(workers=workers, scheduler=scheduler)
    return wants_engine(list(inputs), opts, LOG_EXTENSIONS)


def _command(name: str) -> Any:
    if name == "detect":
        from stemmap.cli._detect import detect

        return detect
    if name == "map":
        from stemmap.cli._map import map_command

        return map_command
    raise ValueError(f"unknown command {name!r}")


def _product_counts(command: str, product: Path) -> dict[str, Any]:
    """The summary counts of one log's finished products."""
    if command == "detect":
        import numpy as np

        from stemmap.io.maps import read_observations_csv

        obs = read_observations_csv(product)
        return {"n_observations": len(obs), "n_scans": len(np.unique(obs.index))}
    m = json.loads((product / "metrics.json").read_text(encoding="utf-8"))
    ft = m.get("false_trees") or {}
    motion = m.get("motion") or {}
    return {
        "n_trees": m.get("n_trees"),
        "n_observations": m.get("detections"),
        "backend": (m.get("backend_stats") or {}).get("backend"),
        # the ray-cast false-tree removal's count only where it ran (forestrix on raw scans)
        "false_trees_removed": ft.get("removed") if ft.get("ran") else None,
        "duplicates_1m": m.get("duplicates_1m"),
        "associated_fraction": (m.get("uncertainty") or {}).get("associated_fraction"),
        "motion_source": motion.get("source"),
        "distance_m": motion.get("distance_m"),
        "drift_estimate_percent": motion.get("drift_estimate_percent"),
    }


def run_log_command(command: str, params: dict[str, Any]) -> dict[str, Any]:
    """Run the single-log ``command`` (``"detect"`` / ``"map"``) with ``params`` in this
    process (a Dask worker); its terminal output is captured. Returns the seconds taken and
    the product's counts.

    Raises
    ------
    LogError
        The command reported an ``error:`` (its text) or exited non-zero.
    """
    fn = _command(command)
    buf = io.StringIO()
    t0 = time.perf_counter()
    try:
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            fn(**params)
    except typer.Exit as exc:
        if exc.exit_code:
            errors = [ln for ln in buf.getvalue().splitlines() if ln.startswith("error:")]
            msg = errors[-1][len("error:") :].strip() if errors else buf.getvalue().strip()
            raise LogError(msg or f"exit code {exc.exit_code}") from None
    seconds = time.perf_counter() - t0
    return {"seconds": round(seconds, 3), **_product_counts(command, params[_OUT_PARAM[command]])}


def _per_log_params(
    command: str, params: dict[str, Any], log: Path, folder: Path
) -> dict[str, Any]:
    """The single-log command's parameters for ``log`` writing into ``folder`` (absolute
    paths: a remote worker's working folder is not ours)."""
    log, folder = log.absolute(), folder.absolute()
    p = {k: v.absolute() if isinstance(v, Path) else v for k, v in params.items()}
    p[_INPUT_PARAM[command]] = [log]
    p["workers"] = None
    p["scheduler"] = None
    if command == "detect":
        p["out_path"] = folder / "observations.csv"
        if p.get("rejected") is not None:
            p["rejected"] = folder / Path(p["rejected"]).name
    else:
        p["out_dir"] = folder
        p["as_json"] = False
    p["quiet"] = True  # a log's terminal output is captured; only its error line is kept
    return p


def _write_summary(path: Path, rows: list[dict[str, Any]]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=SUMMARY_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in SUMMARY_COLUMNS})


def _print_summary(command: str, rows: list[dict[str, Any]], out_dir: Path) -> None:
    from rich.table import Table

    t = Table(title=f"stemmap {command}: {len(rows)} logs -> {out_dir}")
    cols = ["log", "status", "seconds", "n_observations"]
    cols += ["n_scans"] if command == "detect" else ["n_trees", "false_trees_removed"]
    cols.append("error")
    for c in cols:
        t.add_column(c, overflow="fold")
    for r in rows:
        t.add_row(*("" if r.get(c) is None else str(r.get(c)) for c in cols))
    out.print(t)


def run_many_logs(command: str, params: dict[str, Any], *, as_json: bool = False) -> None:
    """Run ``command`` once per log of ``params``'s inputs on the Dask engine (see the
    module docstring); write and print the summary; exit 1 if any log failed.

    Raises
    ------
    typer.Exit
        Code 2 on bad input or options (an ``error:`` line), 1 if any log failed.
    """
    from stemmap.engine.logs import expand_logs, log_names, run_logs
    from stemmap.io.products import run_products

    out_dir = Path(params[_OUT_PARAM[command]])
    workers, scheduler = params.get("workers"), params.get("scheduler")
    quiet = bool(params.get("quiet"))
    with fail_on_stemmap_error():
        if workers is not None and scheduler is not None:
            raise ConfigError("give --workers (a local cluster) or --scheduler, not both.")
        for key, flag in _SINGLE_LOG_OPTIONS[command].items():
            if params.get(key):
                raise ConfigError(f"{flag} takes one log; it cannot be given with several logs.")
        if out_dir.suffix.lower() == ".csv":
            raise ConfigError(
                f"with several logs --out is a folder (one sub-folder per log), got {out_dir}."
            )
        logs = expand_logs(params[_INPUT_PARAM[command]] or [])
        names = log_names(logs)
        tasks = [
            (n, p, (command, _per_log_params(command, params, p, out_dir / n)))
            for n, p in zip(names, logs, strict=True)
        ]
        rows: list[dict[str, Any]] = []
        with progress(not (as_json or quiet)) as bar:
            bar_task = bar.add_task(f"{command}: logs", total=len(tasks))
            outcomes = run_logs(
                run_log_command,
                tasks,
                workers=workers,
                scheduler=scheduler,
                on_done=lambda oc: bar.advance(bar_task),
            )
        for oc in outcomes:
            row: dict[str, Any] = {
                "log": oc.name,
                "input": str(oc.path),
                "status": "done" if oc.ok else "failed",
                "output": str(out_dir / oc.name) if oc.ok else "",
                "error": oc.error.removeprefix("LogError: "),
            }
            if oc.ok:
                row.update(oc.value)
            else:  # the folder a failed log's run created, if it left it empty
                with contextlib.suppress(OSError):
                    (out_dir / oc.name).rmdir()
            rows.append(row)
        summary = out_dir / "summary.csv"
        with run_products(command, inputs=logs, outputs=[summary]) as run:
            _write_summary(run.path(summary), rows)
    failed = [r for r in rows if r["status"] != "done"]
    if as_json:
        out.print_json(json.dumps({"summary": str(summary), "logs": rows}))
    elif not quiet:
        _print_summary(command, rows, out_dir)
        for r in failed:
            print_error(f"log {r['input']}: {r['error']}")
    if failed:
        print_error(
            f"{len(failed)} of {len(rows)} logs failed (see {summary}); the others' products "
            "are written."
        )
        raise typer.Exit(code=1)
