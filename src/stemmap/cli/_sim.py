"""``stemmap sim``: simulated sensor data with ground truth, and scoring against it.

``stemmap sim score stems.csv --run run.npz`` scores per-scan detections (``stemmap detect``
output) against the truth files of a ``stemmap sim scans`` run.

``stemmap sim scans --out run.npz`` simulates a stand and a drive through it and writes

* ``run.npz`` -- the scans (``ranges`` (S, N) metres, inf = no return, ``time`` (S,),
  ``angle_min``, ``angle_increment``, ``range_min``, ``range_max``), via
  :func:`stemmap.io.scans.write_scans_npz`;
* ``run_trees.csv`` -- ground-truth trees ``id,x,y,diameter`` (world frame, metres);
* ``run_poses.csv`` -- the true sensor pose of every scan ``time_s,x,y,theta`` (world frame);
* ``run_odometry.csv`` -- noisy wheel odometry ``time_s,speed,yaw_rate`` (m/s, rad/s; controls
  held until the next row);
* ``run_gnss.csv`` -- noisy GNSS fixes of the vehicle ``time,x,y,sigma`` (world frame, m);
* ``run_truth.npz`` -- per-beam ground truth (``hit_ids``, ``mixed``), wheel odometry (noisy
  and true), non-tree objects, and the scenario parameters as JSON text.
"""

from __future__ import annotations

import json
import math
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from stemmap.cli._common import QuietFlag, fail_on_stemmap_error, out
from stemmap.cli._validate import bounded
from stemmap.io._util import check_npz_sizes, existing_file

if TYPE_CHECKING:
    from stemmap.eval.detection import DetectionMetrics

__all__ = ["register"]

sim_app = typer.Typer(
    name="sim",
    help="Simulate sensor data with ground truth (stands, drives, 2D scans, odometry).",
    no_args_is_help=True,
)


class Layout(StrEnum):
    random = "random"
    clustered = "clustered"
    rows = "rows"


class PathKind(StrEnum):
    loop = "loop"
    lawnmower = "lawnmower"
    straight = "straight"


def _sibling(path: Path, suffix: str) -> Path:
    return path.with_name(f"{path.stem}_{suffix}")


@sim_app.command("scans")
def scans(
    out_path: Annotated[Path, typer.Option("--out", "-o", help="Scans NPZ to write.")],
    preset: Annotated[str, typer.Option(help="Scanner preset: sick_lms, rplidar.")] = "sick_lms",
    seed: Annotated[
        int,
        typer.Option(help="Random seed (same seed, same files).", callback=bounded("--seed", ge=0)),
    ] = 0,
    n_scans: Annotated[
        int | None,
        typer.Option(
            "--n-scans",
            help="Number of scans (default: one pass along the path).",
            callback=bounded("--n-scans", ge=2),
        ),
    ] = None,
    layout: Annotated[Layout, typer.Option(help="Stand layout.")] = Layout.random,
    n_trees: Annotated[
        int,
        typer.Option("--n-trees", help="Trees in the stand.", callback=bounded("--n-trees", ge=1)),
    ] = 60,
    size: Annotated[
        float,
        typer.Option(
            help="Stand side length, metres (square), > 4.", callback=bounded("--size", gt=4)
        ),
    ] = 40.0,
    path: Annotated[PathKind, typer.Option("--path", help="Drive pattern.")] = PathKind.loop,
    speed: Annotated[
        float, typer.Option(help="Vehicle speed, m/s.", callback=bounded("--speed", gt=0))
    ] = 1.0,
    rate_hz: Annotated[
        float | None,
        typer.Option(
            "--rate-hz",
            help="Scan rate (default: the preset's).",
            callback=bounded("--rate-hz", gt=0),
        ),
    ] = None,
    clutter: Annotated[
        bool, typer.Option("--clutter/--no-clutter", help="Bushes, branches, walls, rocks.")
    ] = True,
    noncircular: Annotated[
        bool, typer.Option("--noncircular/--circular", help="Elliptic, rough-barked trunks.")
    ] = False,
    motion_skew: Annotated[
        bool,
        typer.Option("--motion-skew/--no-motion-skew", help="Cast each beam from its own pose."),
    ] = False,
    odometry: Annotated[
        str, typer.Option(help="Wheel-odometry noise preset: none, wheel, forest.")
    ] = "wheel",
    trees_out: Annotated[
        Path | None, typer.Option(help="Truth trees CSV (default: OUT's stem + _trees.csv).")
    ] = None,
    poses_out: Annotated[
        Path | None, typer.Option(help="True sensor poses CSV (default: OUT's stem + _poses.csv).")
    ] = None,
    quiet: QuietFlag = False,
) -> None:
    """Simulate a drive through a stand and write scans + ground truth.

    Writes OUT (e.g. run.npz: the scans) and beside it run_trees.csv (true trees),
    run_poses.csv (true sensor poses), run_odometry.csv (noisy wheel odometry, the input of
    `stemmap map run.npz`), run_gnss.csv, run_truth.npz and run.npz.run.json. Columns:
    docs/outputs.md and the module doc.

    Example: stemmap sim scans --out run.npz --preset sick_lms --seed 1 --n-scans 2000
    """
    from stemmap.errors import ConfigError
    from stemmap.io.atomic import atomic_write
    from stemmap.io.products import run_products
    from stemmap.io.scans import write_scans_npz
    from stemmap.io.trajectory import write_trajectory_csv
    from stemmap.sim import (
        add_clutter,
        clustered_stand,
        lawnmower_path,
        loop_path,
        make_trunks_noncircular,
        random_stand,
        row_stand,
        scanner_preset,
        simulate_run,
        straight_path,
    )

    t_path = trees_out or _sibling(out_path, "trees.csv")
    p_path = poses_out or _sibling(out_path, "poses.csv")
    o_path = _sibling(out_path, "odometry.csv")
    g_path = _sibling(out_path, "gnss.csv")
    truth_path = _sibling(out_path, "truth.npz")
    products = [out_path, t_path, p_path, o_path, g_path, truth_path]
    with fail_on_stemmap_error(), run_products("sim scans", outputs=products) as run:
        gen = np.random.default_rng(seed)
        row_gap = size / 5
        g_stand, g_clutter, g_shape, g_run = gen.spawn(4)
        if layout is Layout.random:
            stand = random_stand(n_trees, (size, size), rng=g_stand)
        elif layout is Layout.clustered:
            stand = clustered_stand(n_trees, (size, size), rng=g_stand)
        else:
            per_row = max(1, round(math.sqrt(n_trees)))
            n_rows = max(1, math.ceil(n_trees / per_row))
            row_gap = size / (n_rows + 1)
            stand = row_stand(
                n_rows,
                per_row,
                row_spacing=size / (n_rows + 1),
                tree_spacing=size / (per_row + 1),
                origin=(size / (per_row + 1), size / (n_rows + 1)),
                rng=g_stand,
            )
        if clutter:
            k = max(1, n_trees // 10)
            stand = add_clutter(
                stand, n_bushes=k, n_branches=k, n_walls=1, n_fences=1, n_rocks=k, rng=g_clutter
            )
        if noncircular:
            stand = make_trunks_noncircular(stand, rng=g_shape)
        model = scanner_preset(preset)
        rate = model.scan_rate_hz if rate_hz is None else rate_hz
        c = np.array([size / 2, size / 2])
        if path is PathKind.loop:
            lap = loop_path(c, (0.35 * size, 0.3 * size))
            lap_len = float(np.sum(np.hypot(*np.diff(lap, axis=0).T)))
            laps = 1.0
            if n_scans is not None:
                laps = max(1.0, math.ceil(n_scans / (lap_len / speed * rate) * 1.05 + 0.05))
            wp = loop_path(c, (0.35 * size, 0.3 * size), laps=laps)
        elif path is PathKind.lawnmower:
            # rows stand at y = k * gap (k = 1..n_rows): strips half a gap off drive between them
            gap = row_gap if layout is Layout.rows else size / 5
            wp = lawnmower_path((0.0, 0.0, size, size), gap, margin=gap / 2)
        else:
            wp = straight_path((0.1 * size, 0.1 * size), (0.9 * size, 0.9 * size))
        sim = simulate_run(
            stand,
            wp,
            scanner=model,
            speed=speed,
            rate_hz=rate,
            odometry_noise=odometry,
            corridor_half_width=1.2,
            max_scans=n_scans,
            motion_skew=motion_skew,
            rng=g_run,
        )
        if n_scans is not None and len(sim) < n_scans:
            raise ConfigError(
                f"the {path.value} drive yields only {len(sim)} scans at {rate} Hz and {speed} m/s;"
                " lower --speed, use --path loop, or ask for fewer --n-scans."
            )
        write_scans_npz(run.path(out_path), sim.scans)
        st = sim.stand
        with atomic_write(run.path(t_path)) as fh:
            fh.write("id,x,y,diameter\n")
            for i in range(st.n_trees):
                x, y = st.trees_xy[i]
                fh.write(f"{i},{x:.6f},{y:.6f},{st.diameters[i]:.6f}\n")
        write_trajectory_csv(run.path(p_path), sim.true_poses)
        with atomic_write(run.path(o_path)) as fh:
            fh.write("time_s,speed,yaw_rate\n")
            odo = sim.odometry
            for t, v, w in zip(
                odo.times.tolist(), odo.speed.tolist(), odo.yaw_rate.tolist(), strict=True
            ):
                fh.write(f"{t!r},{v!r},{w!r}\n")
        with atomic_write(run.path(g_path)) as fh:
            fh.write("time,x,y,sigma\n")
            if sim.gnss is not None:
                g = sim.gnss
                for t, (x, y), sg in zip(
                    g.times.tolist(), g.xy.tolist(), g.sigma.tolist(), strict=True
                ):
                    fh.write(f"{t!r},{x!r},{y!r},{sg!r}\n")
        params = dict(sim.params)
        params.update(
            {
                "seed": seed,
                "layout": layout.value,
                "path": path.value,
                "size_m": size,
                "clutter": clutter,
                "noncircular": noncircular,
                "preset": preset,
            }
        )
        with atomic_write(run.path(truth_path), "wb") as fh:
            np.savez_compressed(
                fh,
                hit_ids=sim.hit_ids.astype(np.int32),
                mixed=sim.mixed,
                odom_time=sim.odometry.times,
                odom_speed=sim.odometry.speed,
                odom_yaw_rate=sim.odometry.yaw_rate,
                true_speed=sim.true_odometry.speed,
                true_yaw_rate=sim.true_odometry.yaw_rate,
                clutter_xy=st.clutter_objects_xy,
                clutter_extent=st.clutter_objects_extent,
                clutter_kind=np.array(st.clutter_kinds, dtype=str),
                params_json=np.array(json.dumps(params, default=float)),
            )
        if not quiet:
            out.print(
                f"simulated {len(sim)} scans x {sim.scans.n_beams} beams ({preset}), "
                f"{st.n_trees} trees, {st.n_clutter_objects} non-tree objects\n"
                f"  scans: {out_path}\n  trees: {t_path}\n  poses: {p_path}\n"
                f"  odometry: {o_path}\n  gnss: {g_path}\n  truth: {truth_path}"
            )


def _read_truth_trees(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read an ``id,x,y,diameter`` truth CSV written by ``stemmap sim scans``."""
    from stemmap.errors import InputError

    existing_file(path, "truth trees CSV")
    try:
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise InputError(f"truth trees CSV {str(path)!r} is malformed: {exc}") from exc
    if table.shape[1] != 4 or not np.all(np.isfinite(table)):
        raise InputError(
            f"truth trees CSV {str(path)!r} must have finite columns id,x,y,diameter; "
            f"got {table.shape[1]} columns."
        )
    order = np.argsort(table[:, 0])
    if not np.array_equal(table[order, 0], np.arange(table.shape[0])):
        raise InputError(f"truth trees CSV {str(path)!r}: ids must be 0..T-1.")
    return table[order, 1:3], table[order, 3]


def _print_scores(m: DetectionMetrics) -> None:
    """The ``sim score`` summary on stdout: counts, rates, centre and DBH error, and recall /
    DBH error per range bin that holds truth trees (``m``: the scorer's metrics)."""

    def cm(v: float) -> str:
        return "n/a" if not math.isfinite(v) else f"{100 * v:.2f} cm"

    def ratio(v: float) -> str:
        return "n/a" if not math.isfinite(v) else f"{v:.3f}"

    out.print(
        f"{m.n_frames} scans, {m.n_detections} detections: TA {m.ta}, FA {m.fa}, FR {m.fr}, "
        f"TR {m.tr}/{m.n_nontree}\n"
        f"precision {ratio(m.precision)}, recall {ratio(m.recall)}, F1 {ratio(m.f1)}; "
        f"centre RMSE {cm(m.center_rmse)}; DBH RMSE {cm(m.diameter_rmse)}, "
        f"bias {cm(m.diameter_bias)}"
    )
    for b in m.by_range:
        if b.n_truth:
            out.print(
                f"  {b.range_lo:g}-{b.range_hi:g} m: recall {ratio(b.recall)}, "
                f"DBH RMSE {cm(b.diameter_rmse)}, bias {cm(b.diameter_bias)} "
                f"({b.n_truth} trees)"
            )


@sim_app.command("score")
def score(
    detections: Annotated[
        Path, typer.Argument(help="Observations CSV from `stemmap detect` (sensor frame).")
    ],
    run_path: Annotated[
        Path,
        typer.Option(
            "--run", help="The scans NPZ written by `stemmap sim scans` (truth beside it)."
        ),
    ],
    gate: Annotated[
        float, typer.Option(help="Match gate, metres.", callback=bounded("--gate", gt=0))
    ] = 0.5,
    min_returns: Annotated[
        int,
        typer.Option(
            "--min-returns",
            help="Beams a trunk needs to count as detectable.",
            callback=bounded("--min-returns", ge=1),
        ),
    ] = 5,
    max_range: Annotated[
        float,
        typer.Option(
            "--max-range",
            help=(
                "Trees farther than this are don't-care, and detections farther than it plus "
                "--gate are not scored (neither true nor false), m."
            ),
            callback=bounded("--max-range", gt=0),
        ),
    ] = 15.0,
    min_diameter: Annotated[
        float,
        typer.Option(
            "--min-diameter",
            help="Thinner trees are don't-care, m.",
            callback=bounded("--min-diameter", ge=0),
        ),
    ] = 0.10,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the metrics as JSON here.")
    ] = None,
    quiet: QuietFlag = False,
) -> None:
    """Score per-scan detections against the simulator's ground truth (TA/FA/FR/TR, DBH error).

    Example: stemmap sim scans --out run.npz && stemmap detect run.npz --out stems.csv &&
    stemmap sim score stems.csv --run run.npz
    """
    from stemmap.errors import InputError
    from stemmap.eval import score_scan_detections
    from stemmap.io.atomic import atomic_write
    from stemmap.io.maps import read_observations_csv
    from stemmap.io.products import run_products
    from stemmap.io.scans import NPZ_ERRORS, read_scans
    from stemmap.io.trajectory import read_trajectory_csv

    truth_files = [_sibling(run_path, s) for s in ("trees.csv", "poses.csv", "truth.npz")]
    with (
        fail_on_stemmap_error(),
        run_products(
            "sim score", inputs=[detections, run_path, *truth_files], outputs=[json_out]
        ) as run,
    ):
        batch = read_scans(run_path)
        trees_xy, diam = _read_truth_trees(_sibling(run_path, "trees.csv"))
        poses = read_trajectory_csv(_sibling(run_path, "poses.csv")).poses
        truth_path = _sibling(run_path, "truth.npz")
        existing_file(truth_path, "truth NPZ")
        try:
            with np.load(truth_path, allow_pickle=False) as z:
                check_npz_sizes(z, truth_path, "truth NPZ")
                hit_ids = np.asarray(z["hit_ids"], dtype=np.int64)
                clutter_xy = np.asarray(z["clutter_xy"], dtype=np.float64).reshape(-1, 2)
                clutter_ext = np.asarray(z["clutter_extent"], dtype=np.float64)
        except InputError:
            raise
        except (KeyError, *NPZ_ERRORS) as exc:
            raise InputError(f"truth NPZ {str(truth_path)!r} is unreadable: {exc}") from exc
        if hit_ids.shape != batch.ranges.shape or poses.shape[0] != len(batch):
            raise InputError(
                f"{str(run_path)!r} has {batch.ranges.shape} ranges but the truth has "
                f"{hit_ids.shape} hit ids and {poses.shape[0]} poses; the files do not belong "
                "together."
            )
        obs = read_observations_csv(detections)
        a_max = batch.angle_min + batch.angle_increment * (batch.n_beams - 1)
        m = score_scan_detections(
            obs,
            trees_xy=trees_xy,
            diameters=diam,
            sensor_poses=poses,
            hit_ids=hit_ids,
            nontree_xy=clutter_xy,
            nontree_extent=clutter_ext,
            fov=(min(batch.angle_min, a_max), max(batch.angle_min, a_max), batch.angle_increment),
            gate=gate,
            min_returns=min_returns,
            max_range=max_range,
            min_diameter=min_diameter,
        )
        d = m.to_dict()
        d["eligibility"] = {
            "min_returns": min_returns,
            "max_range_m": max_range,
            "min_diameter_m": min_diameter,
        }
        if json_out is not None:
            with atomic_write(run.path(json_out)) as fh:
                json.dump(d, fh, indent=2)

        if not quiet:  # the metrics file (--json) is the product, written either way
            _print_scores(m)


def register(app: typer.Typer) -> None:
    """Add the ``sim`` command group to the ``stemmap`` app."""
    from stemmap.cli._sim_munjer import munjer

    sim_app.command("munjer")(munjer)
    app.add_typer(sim_app, name="sim")
