"""Terminal output of the product-writing commands: a rich summary table for people, ``--json``
for machines, and the first-run numba compile announcement."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Annotated, Any

import typer

from stemmap.cli._common import clean_json, console, json_default, out

__all__ = ["JsonFlag", "announce_compile", "compile_notice", "fmt", "print_summary"]

JsonFlag = Annotated[
    bool,
    typer.Option(
        "--json",
        help="Print one JSON object (the summary, the metrics and the files written) on stdout "
        "instead of the table.",
    ),
]

#: Modules whose numba kernels compile on first use. The SLAM kernels are per back-end: a
#: back-end compiles only its own, so asking about the others would announce a "first run" on
#: every run of a user who never uses them (the iSAM2 demo compiles ``_isam2_track`` only:
#: measured with an empty ``NUMBA_CACHE_DIR``, Dec 3).
_KERNEL_MODULES = {
    "scan": ("stemmap.scan._detect_fast", "stemmap.scan._fit_geometric"),
    "cloud": ("stemmap.cloud._grid_kernel", "stemmap.cloud.slicefit"),
}
_BACKEND_KERNELS = {
    "isam2": ("stemmap.slam._isam2_track",),
    "forestrix": ("stemmap.slam._isam2_track",),
    # (both smooth by default: the smoother's band solve, stemmap.slam._band_kernel)
    "ekf": ("stemmap.slam._association_kernel", "stemmap.slam._band_kernel"),
    "fastslam": ("stemmap.slam._fastslam_kernel", "stemmap.slam._band_kernel"),
    "treedb": (),
}


def _has_cache(src: Path) -> bool:
    """Whether numba has an index file for a kernel defined in ``src``: beside it, or under
    ``NUMBA_CACHE_DIR`` when that is set (numba keeps one sub-folder per source folder there,
    named after the folder and a hash of its path)."""
    root = os.environ.get("NUMBA_CACHE_DIR")
    pattern = f"{src.stem}.*.nbi"
    if root:
        return any(Path(root).glob(f"{src.parent.name}_*/{pattern}"))
    return any((src.parent / "__pycache__").glob(pattern))


def announce_compile(*areas: str, backend: str | None = None, quiet: bool = False) -> None:
    """Tell the user (stderr) when the numba kernels of ``areas`` (``scan``) and of the SLAM
    ``backend`` have no on-disk cache yet: the first run then compiles them (about a minute on
    a loaded 2-core machine) without any other sign of life. Nothing under ``-q`` (``quiet``)."""
    if quiet:
        return
    import importlib.util

    missing = []
    names = [n for a in areas for n in _KERNEL_MODULES.get(a, ())]
    names += _BACKEND_KERNELS.get(backend or "", ())
    for name in names:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            continue
        src = Path(spec.origin)
        if not _has_cache(src):
            missing.append(name.rsplit(".", 1)[1])
    if missing:
        console.print(
            f"[cyan]first run:[/cyan] compiling numba kernels ({', '.join(missing)}); this takes "
            "about a minute once and is cached for later runs."
        )


def compile_notice(
    *areas: str, backend: str | None = None, quiet: bool = False
) -> Callable[[], None]:
    """:func:`announce_compile` as a callable that speaks at most once: a command calls it
    right before its first kernel call, once its inputs are read and its options checked, so
    a bad input or option is reported before (and instead of) the first-run notice."""
    done: list[bool] = []

    def notice() -> None:
        if not done:
            done.append(True)
            announce_compile(*areas, backend=backend, quiet=quiet)

    return notice


def fmt(v: Any, unit: str = "", scale: float = 1.0, digits: int = 2) -> str:
    """A number for the table: ``n/a`` for None / NaN, else scaled and rounded with its unit."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return str(v)
    if isinstance(v, int) and scale == 1.0:
        return f"{v}{unit}"
    return f"{scale * float(v):.{digits}f}{unit}"


def print_summary(
    title: str,
    rows: Sequence[tuple[str, str, str]],
    out_dir: Path | None,
    files: Sequence[str],
    *,
    as_json: bool,
    payload: dict[str, Any],
    quiet: bool = False,
) -> None:
    """The run's summary: ``rows`` (quantity, value, where in metrics.json) as a table, or
    ``payload`` + ``files`` as one JSON object (``--json``, printed with ``quiet`` too: it is
    the output asked for); nothing when ``quiet`` without ``as_json``."""
    if as_json:
        doc = {"summary": {r[0]: r[1] for r in rows}, **payload, "files": list(files)}
        if out_dir is not None:
            doc["out_dir"] = str(out_dir)
        typer.echo(json.dumps(clean_json(doc), default=json_default))
        return
    if quiet:
        return
    from rich.table import Table

    table = Table(title=title, title_justify="left", show_lines=False)
    # the quantity (prose) wraps; the key keeps a readable width, so a narrow or non-tty
    # console (80 columns) never folds a key letter by letter
    table.add_column("quantity", ratio=3)
    table.add_column("value", justify="right", no_wrap=True)
    table.add_column("metrics.json key", style="dim", overflow="fold", ratio=2, min_width=22)
    for name, value, key in rows:
        table.add_row(name, value, key)
    out.print(table)
    where = f"{out_dir}/: " if out_dir is not None else ""
    out.print(f"wrote {where}{' '.join(files)}", markup=False, soft_wrap=True)


def run_warnings(m: dict[str, Any], crs: str | None) -> list[str]:
    """Things a reader of the report should know about the run."""
    w = []
    if crs is None:
        w.append(
            "no CRS: coordinates are metres in a local frame (declared as such in the GeoJSON "
            "and GeoPackage); pass --crs if the odometry frame is georeferenced."
        )
    if m.get("n_trees", 1) == 0:
        w.append("the map has no trees.")
    if m.get("duplicates_1m"):
        w.append(f"{m['duplicates_1m']} pairs of mapped trees are closer than 1 m (duplicates?).")
    if "ate_error" in m:
        w.append(f"no ATE against GPS: {m['ate_error']}")
    return w


def write_run_report(
    out_dir: Path,
    *,
    title: str,
    headline: str,
    metrics: dict[str, Any],
    figure: str,
    stem_map: Any,
    parameters: dict[str, Any],
    files: Sequence[str],
    crs: str | None,
) -> str:
    """``report.html`` of a map / demo run in ``out_dir`` (figure = the PNG written there);
    returns its name."""
    from stemmap.io.maps import TREE_CSV_COLUMNS, tree_rows
    from stemmap.viz.report import write_report

    doc = json.loads(json.dumps(clean_json(metrics), default=json_default))
    rows = [
        [round(v, 4) if isinstance(v, float) and math.isfinite(v) else v for v in r]
        for r in tree_rows(stem_map)
    ]
    write_report(
        out_dir / "report.html",
        title=title,
        headline=headline,
        metrics=doc,
        figure_png=(out_dir / figure).read_bytes(),
        diameters=stem_map.diameters,
        table_header=TREE_CSV_COLUMNS,
        table_rows=rows,
        parameters=parameters,
        warnings=run_warnings(doc, crs),
        files=files,
    )
    return "report.html"
