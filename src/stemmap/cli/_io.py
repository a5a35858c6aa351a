"""``stemmap io``: inspect bags and convert scan files between formats.

* ``stemmap io topics BAG`` -- the topics of a ROS1 / ROS2 bag with types and message counts.
* ``stemmap io convert-scans SRC --out DST`` -- 2D scans from NPZ, CSV or a bag to NPZ or CSV
  (the layouts of docs/algorithms/io.md); damaged frames are reported and skipped.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stemmap.cli._common import QuietFlag, console, fail_on_stemmap_error, out

__all__ = ["register"]

io_app = typer.Typer(
    name="io",
    help="Inspect ROS bags and convert scan files (NPZ, CSV, ROS1/ROS2 bags).",
    no_args_is_help=True,
)


@io_app.command("topics")
def topics(
    bag: Annotated[
        Path, typer.Argument(help="ROS1 .bag, ROS2 bag folder, or ROS2 .db3 / .mcap file.")
    ],
) -> None:
    """List the topics of a bag with their message types and counts.

    Example: stemmap io topics run.bag
    """
    from rich.table import Table

    from stemmap.io.rosbag import bag_summary

    with fail_on_stemmap_error():
        rows = bag_summary(bag)
    table = Table(title=str(bag))
    table.add_column("topic")
    table.add_column("type")
    table.add_column("messages", justify="right")
    for r in rows:
        table.add_row(r.topic, r.msgtype, str(r.n_messages))
    out.print(table)


@io_app.command("convert-scans")
def convert_scans(
    src: Annotated[
        Path, typer.Argument(help="Scans: .npz, .csv, ROS1 .bag or ROS2 bag (folder/.db3/.mcap).")
    ],
    out_path: Annotated[
        Path,
        typer.Option(
            "--out",
            "-o",
            help="Output: .npz, .csv, ROS1 .bag, or a suffix-less path for a ROS2 bag folder.",
        ),
    ],
    topic: Annotated[
        str | None, typer.Option(help="LaserScan topic of a bag (default: the only one).")
    ] = None,
    out_topic: Annotated[
        str, typer.Option("--out-topic", help="Topic name when writing a bag.")
    ] = "/scan",
    storage: Annotated[
        str, typer.Option(help="ROS2 storage when writing a ROS2 bag: sqlite3 or mcap.")
    ] = "sqlite3",
    range_unit: Annotated[
        str | None,
        typer.Option(
            help="Unit of the input's ranges: m, cm, mm, ft or us-ft; the output is in metres "
            "[default: m; scans whose median return is beyond 500 m are refused without it]."
        ),
    ] = None,
    quiet: QuietFlag = False,
) -> None:
    """Convert 2D laser scans between NPZ, CSV and ROS bags (dominant beam geometry kept).

    Examples: stemmap io convert-scans run.bag --topic /scan --out run.npz;
    stemmap io convert-scans run.npz --out run_ros2 --storage mcap
    """
    from stemmap.errors import InputError
    from stemmap.io.products import run_products
    from stemmap.io.rosbag import write_scans_bag
    from stemmap.io.scans import SkippedFrame, read_scans, write_scans_csv, write_scans_npz

    with (
        fail_on_stemmap_error(),
        run_products("io convert-scans", inputs=[src], outputs=[out_path]) as run,
    ):
        ext = out_path.suffix.lower()
        if ext not in (".npz", ".csv", ".bag", ""):
            raise InputError(
                f"output {str(out_path)!r} must end in .npz, .csv or .bag, or have no suffix "
                f"(a ROS2 bag folder); got {ext!r}."
            )
        skipped: list[SkippedFrame] = []
        batch = read_scans(src, topic=topic, skipped=skipped, range_unit=range_unit)
        for sk in skipped:
            console.print(
                f"[yellow]skipped frame {sk.frame_index}[/yellow] (t={sk.time:.3f} s): {sk.reason}"
            )
        staged = run.path(out_path)
        if ext == ".npz":
            write_scans_npz(staged, batch)
        elif ext == ".csv":
            write_scans_csv(staged, batch)
        else:
            ros = 1 if ext == ".bag" else 2
            write_scans_bag(staged, batch, topic=out_topic, ros=ros, storage=storage)
    if not quiet:
        out.print(
            f"{len(batch)} scans x {batch.n_beams} beams ({len(skipped)} skipped) -> {out_path}",
            markup=False,
        )


def register(app: typer.Typer) -> None:
    """Add the ``io`` command group to the ``stemmap`` app."""
    app.add_typer(io_app)
