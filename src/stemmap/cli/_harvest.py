"""``stemmap harvest-sim``: a simulated harvester capturing a trunk (Zheng et al. 2012 §5)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from stemmap.cli._common import fail_on_stemmap_error, out
from stemmap.cli._validate import bounded

__all__ = ["register"]


def _tilt_option(flag: str, what: str) -> Any:
    """A scan-plane tilt option in degrees, -30..30."""
    return typer.Option(
        help=f"Scan-plane {what}, degrees, -30..30.", callback=bounded(flag, ge=-30, le=30)
    )


def harvest_sim(
    seed: Annotated[
        int,
        typer.Option(
            help="Random seed of the stand and the noise.", callback=bounded("--seed", ge=0)
        ),
    ] = 1,
    trees: Annotated[
        int,
        typer.Option(help="Trees around the parked machine.", callback=bounded("--trees", ge=1)),
    ] = 25,
    target: Annotated[
        str, typer.Option(help="How to pick the trunk: nearest, index or bearing.")
    ] = "nearest",
    index: Annotated[
        int | None,
        typer.Option(
            help="With --target index: row among the first scan's trunks.",
            callback=bounded("--index", ge=0),
        ),
    ] = None,
    bearing: Annotated[
        float | None,
        typer.Option(
            help="With --target bearing: degrees from the machine's x axis.",
            callback=bounded("--bearing", ge=-180, le=180),
        ),
    ] = None,
    max_cycles: Annotated[
        int,
        typer.Option(
            help="Give up after this many cycles.", callback=bounded("--max-cycles", ge=1)
        ),
    ] = 40,
    roll_deg: Annotated[
        float, _tilt_option("--roll-deg", "roll of the crane-mounted scanner (machine on a slope)")
    ] = 0.0,
    pitch_deg: Annotated[
        float, _tilt_option("--pitch-deg", "pitch of the scanner (the boom's attitude)")
    ] = 0.0,
    imu: Annotated[
        bool,
        typer.Option(
            "--imu/--no-imu",
            help="Give the detector the AHRS roll and pitch (Zheng 2012 §2, eq. 1); "
            "--no-imu detects on the tilted ranges as if level.",
        ),
    ] = True,
    png: Annotated[Path, typer.Option(help="Top-view figure to write.")] = Path("harvest.png"),
) -> None:
    """Simulate a crane-mounted 2D laser guiding the harvesting head to a trunk.

    Each cycle scans (SICK LMS291 set-up of Zheng 2012: 0.25 deg, 100 deg, 8 m), detects the
    trunks, composes the trunk pose relative to the head (eq. 11), plans 10 < k < 100 Cartesian
    set-points within the joint velocity and acceleration limits, executes the first ten, and
    re-scans, until the head is within the capture tolerance. Prints the cycle log and writes a
    PNG. ``--roll-deg`` / ``--pitch-deg`` tilt the scan plane; the AHRS reading (true tilt
    plus 0.2 deg noise) goes to the detector unless ``--no-imu``.

    Example: stemmap harvest-sim --seed 3 --target bearing --bearing 30 --png capture.png
    """
    from stemmap.harvester.capture import ScannerMount, warm_up_planner
    from stemmap.harvester.kinematics import ForestryCrane
    from stemmap.harvester.simulate import harvester_stand, simulate_capture
    from stemmap.io.products import run_products
    from stemmap.viz.harvester import plot_capture

    if target not in ("nearest", "index", "bearing"):
        raise typer.BadParameter("use nearest, index or bearing", param_hint="--target")
    if target == "bearing" and bearing is None:
        raise typer.BadParameter(
            "--target bearing needs --bearing DEGREES (from the machine's x axis, -180..180).",
            param_hint="--bearing",
        )
    if target == "index" and index is None:
        raise typer.BadParameter("--target index needs --index ROW (>= 0).", param_hint="--index")
    with fail_on_stemmap_error(), run_products("harvest-sim", outputs=[png]) as run:
        crane = ForestryCrane()
        warm_up_planner()  # a controller compiles before its first control period
        stand = harvester_stand(trees, rng=seed)
        result = simulate_capture(
            stand,
            crane=crane,
            mode=target,  # type: ignore[arg-type]
            index=index,
            bearing=None if bearing is None else math.radians(bearing),
            max_cycles=max_cycles,
            mount=ScannerMount(roll=math.radians(roll_deg), pitch=math.radians(pitch_deg)),
            use_imu=imu,
            rng=seed + 1000,
        )
        table = Table(title="capture cycles")
        for col in ("cycle", "trunks", "target x, y (m)", "seen", "dist (m)", "k", "plan (ms)"):
            table.add_column(col, justify="right")
        for c in result.log:
            table.add_row(
                str(c.cycle),
                str(c.n_trunks),
                f"{c.target_xy[0]:.2f}, {c.target_xy[1]:.2f}",
                "yes" if c.target_seen else "no",
                f"{c.distance:.3f}",
                str(c.k),
                f"{c.planning_ms:.2f}",
            )
        out.print(table)
        plot_capture(run.path(png), stand, result, crane)
        err = f"{result.final_error * 100:.1f} cm" if math.isfinite(result.final_error) else "n/a"
        out.print(
            f"{'CAPTURED' if result.success else 'FAILED: ' + result.reason}; "
            f"final error {err}; cycles {result.cycles}; figure {png}"
        )
    if not result.success:
        raise typer.Exit(code=1)


def register(app: typer.Typer) -> None:
    app.command("harvest-sim")(harvest_sim)
