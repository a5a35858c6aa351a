"""``stemmap stems``: stem positions and DBH from a 3D point cloud."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from stemmap.cli._catalog import (
    CATALOG_UP_AXIS_NOTE,
    EngineOptions,
    catalog_sample,
    run_catalog_stems,
    wants_engine,
)
from stemmap.cli._common import QuietFlag, console, fail_on_stemmap_error, progress
from stemmap.cli._geo import checked_crs
from stemmap.cli._stems_base import (
    base_warning,
    empty_result_notes,
    height_payload,
    height_reference,
)
from stemmap.cli._summary import JsonFlag, compile_notice, fmt, print_summary
from stemmap.cli._validate import bounded
from stemmap.cloud.ground import DEFAULT_MAX_MEMORY, GroundModel
from stemmap.errors import ConfigError

if TYPE_CHECKING:
    from stemmap.cloud.sensor import SensorPositions

__all__ = ["register"]


def _floats(text: str, option: str, form: str, sizes: tuple[int, ...]) -> tuple[float, ...]:
    """'a,b[,c]' -> floats; ConfigError naming the option and the expected form otherwise."""
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) not in sizes or not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"{option} must be {form} in metres, got {text!r}.")
    return vals


def _sensor(
    origin: str | None,
    trajectory: Path | None,
    time_field: str | None,
    time_offset: float,
    sensor_offset: str | None,
    convention: Any = None,
) -> SensorPositions | None:
    """The sensor positions the options describe (None without --origin / --trajectory).
    ``convention``: the cloud's units and up axis; --origin is in the file's own frame and
    units and is converted with the cloud (three values when the up axis is not z)."""
    from stemmap.cloud.sensor import SensorPositions

    if origin is not None and trajectory is not None:
        raise ConfigError("give either --origin (one station) or --trajectory, not both.")
    if trajectory is None:
        used = [
            n
            for n, v in (
                ("--time-field", time_field),
                ("--time-offset", time_offset or None),
                ("--sensor-offset", sensor_offset),
            )
            if v is not None
        ]
        if used:
            raise ConfigError(f"{', '.join(used)} only apply with --trajectory.")
        if origin is None:
            return None
        station = _floats(origin, "--origin", "'X,Y' or 'X,Y,Z'", (2, 3))
        if convention is not None and not convention.is_identity:
            import numpy as np

            if len(station) == 2 and convention.up_axis != "z":
                raise ConfigError(
                    f"--origin needs 'X,Y,Z' (the file's frame) with --up-axis "
                    f"{convention.up_axis}: the file's x, y are not both horizontal."
                )
            pad = station if len(station) == 3 else (*station, 0.0)
            turned = convention.apply(np.array([pad], dtype=np.float64))[0]
            station = tuple(float(v) for v in turned[: len(station)])
        return SensorPositions(station=station)
    from stemmap.io.trajectory import read_trajectory_csv, read_trajectory_tum

    reader = read_trajectory_csv if trajectory.suffix.lower() == ".csv" else read_trajectory_tum
    off = _floats(sensor_offset, "--sensor-offset", "'A,B'", (2,)) if sensor_offset else (0.0, 0.0)
    return SensorPositions(
        trajectory=reader(trajectory),
        time_field=time_field,
        time_offset=time_offset,
        sensor_offset=(off[0], off[1]),
    )


def stems(
    clouds: Annotated[
        list[str],
        typer.Argument(
            help="A cloud (LAS/LAZ, PLY, PCD, XYZ text, a ROS bag), or LAS/LAZ tiles: several "
            "files, a folder, a glob ('tiles/*.laz') or a .txt listing paths.",
            show_default=False,
        ),
    ],
    out_csv: Annotated[
        Path, typer.Option("--out", "-o", help="CSV to write, one row per stem.")
    ] = Path("stems.csv"),
    preset: Annotated[
        str, typer.Option(help="Method: ours (default), ours_kasa or munjer2025.")
    ] = "ours",
    geojson: Annotated[Path | None, typer.Option(help="Also write a GeoJSON of the stems.")] = None,
    png: Annotated[Path | None, typer.Option(help="Also write a top-view PNG.")] = None,
    report: Annotated[
        Path | None,
        typer.Option(
            help="Also write a self-contained HTML report (figure, DBH histogram, table)."
        ),
    ] = None,
    gpkg: Annotated[
        Path | None,
        typer.Option(
            help="Also write a GeoPackage (layer 'stems') in the cloud's CRS.",
            rich_help_panel="Georeferencing",
        ),
    ] = None,
    crs: Annotated[
        str | None,
        typer.Option(
            help="CRS of the cloud's x, y (EPSG code, WKT, PROJ) [default: the LAS/LAZ "
            "header's CRS; none: a local frame]. With --up-axis y or x: the CRS of the "
            "turned frame's x, y (a header's CRS is then not used).",
            rich_help_panel="Georeferencing",
        ),
    ] = None,
    topic: Annotated[str | None, typer.Option(help="PointCloud2 topic (bags only).")] = None,
    heights: Annotated[
        bool, typer.Option(help="Estimate stem (tree) heights: highest point within 1 m (ours).")
    ] = True,
    max_memory: Annotated[
        float,
        typer.Option(
            help="Memory budget in GB for the run's rasters (ground grid, clustering grid); a "
            "cloud that needs more is refused with an error (tile it)."
        ),
    ] = DEFAULT_MAX_MEMORY / 1e9,
    profile: Annotated[
        Path | None,
        typer.Option(
            help="Write the stem profiles (diameter every 0.5 m up the visible stem, with std) "
            "to this CSV (ours).",
            rich_help_panel="Forestry products",
        ),
    ] = None,
    metrics: Annotated[
        Path | None,
        typer.Option(
            help="Write a JSON with the plot summary (stems/ha, basal area m2/ha, quadratic "
            "mean diameter, DBH histogram) and per-tree DBH, height and stem volume (ours).",
            rich_help_panel="Forestry products",
        ),
    ] = None,
    dtm: Annotated[
        Path | None,
        typer.Option(
            help="Write the terrain model (the ground raster heights are measured from) as a "
            "float32 GeoTIFF in the cloud's CRS, nodata where no point fell (ours).",
            rich_help_panel="Forestry products",
        ),
    ] = None,
    labels: Annotated[
        Path | None,
        typer.Option(
            help="Write the cloud as LAS with a tree_id extra dimension (0 = ground or no tree; "
            "i = row i-1 of the CSV) (ours).",
            rich_help_panel="Forestry products",
        ),
    ] = None,
    read_points: Annotated[
        int,
        typer.Option(
            help="Points per block when streaming LAS/LAZ.", callback=bounded("--read-points", ge=1)
        ),
    ] = 2_000_000,
    chunk_size: Annotated[
        float | None,
        typer.Option(
            help="Side (m) of the square processing chunks of a tile catalog [default: from "
            "the point density, ~8 M points per buffered chunk].",
            callback=bounded("--chunk-size", gt=0),
            rich_help_panel="Tile catalogs (Dask engine)",
        ),
    ] = None,
    buffer: Annotated[
        float | None,
        typer.Option(
            help="Buffer (m) read around each chunk [default: 5]; stems belong to the chunk "
            "holding their centre.",
            callback=bounded("--buffer", ge=0),
            rich_help_panel="Tile catalogs (Dask engine)",
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="Worker processes of the local Dask cluster [default: one per core].",
            callback=bounded("--workers", ge=1),
            rich_help_panel="Tile catalogs (Dask engine)",
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Submit to a running Dask scheduler tcp://HOST:PORT instead (the work folder "
            "must be shared with its workers).",
            rich_help_panel="Tile catalogs (Dask engine)",
        ),
    ] = None,
    resume: Annotated[
        bool,
        typer.Option(
            help="Skip chunks the work folder's manifest records as done with the same inputs "
            "and parameters.",
            rich_help_panel="Tile catalogs (Dask engine)",
        ),
    ] = False,
    work: Annotated[
        Path | None,
        typer.Option(
            help="Work folder for chunk results and the manifest: new, empty or an earlier "
            "run's (a folder holding other files is refused) [default: OUT's name + '_chunks' "
            "beside it].",
            rich_help_panel="Tile catalogs (Dask engine)",
        ),
    ] = None,
    origin: Annotated[
        str | None,
        typer.Option(
            help="Scanner position 'X,Y[,Z]' of a single-station scan, in the cloud file's "
            "own coordinates (converted with --units / --up-axis; 'X,Y,Z' when the up axis "
            "is not z): fits along the rays (ours).",
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = None,
    trajectory: Annotated[
        Path | None,
        typer.Option(
            help="Machine path, stemmap CSV time_s,x,y,theta (.csv) or TUM 't x y z qx qy qz qw'; "
            "each point's sensor position is interpolated at its time stamp (ours).",
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = None,
    time_field: Annotated[
        str | None,
        typer.Option(
            help="Per-point time field [default: gps_time, time or timestamp, the first present].",
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = None,
    time_offset: Annotated[
        float,
        typer.Option(
            help="Seconds added to the point times before the trajectory look-up (e.g. 1e9 for "
            "LAS adjusted standard GPS time against GPS seconds).",
            callback=bounded("--time-offset"),
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = 0.0,
    sensor_offset: Annotated[
        str | None,
        typer.Option(
            help="Scanner position 'A,B' (m) forward and left of the trajectory's reference "
            "point [default: 0,0].",
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = None,
    units: Annotated[
        str | None,
        typer.Option(
            help="Length unit of the cloud's coordinates: m, cm, mm, ft or us-ft (US survey "
            "foot); converted to metres as read. The CSV, profiles and metrics are in "
            "metres; --geojson, --gpkg and --dtm keep the CRS's own units; tiles are "
            "converted too [default: m; a LAS CRS in another unit is refused without it].",
            rich_help_panel="Input conventions",
        ),
    ] = None,
    up_axis: Annotated[
        str,
        typer.Option(
            help="The cloud's axis that points up: z (LAS, most lidar tools), y "
            "(photogrammetry, Unity, some SLAM exports) or x; results in the turned frame "
            "(y up: file (x, y, z) -> (x, -z, y)). Not guessed: a run of 1-5 stems whose "
            "cloud is shaped like a turned one (a tree lying on its side, a ground plane "
            "standing up) gets a warning; the summary and --json state the axis assumed. "
            "One file only (tiles are refused: turn them first).",
            rich_help_panel="Input conventions",
        ),
    ] = "z",
    as_json: JsonFlag = False,
    quiet: QuietFlag = False,
) -> None:
    """Find the stems in a point cloud (or LAS/LAZ tiles): one CSV row per stem, position + DBH.

    Columns x, y, z, diameter, n_points, quality, ... per stem (cloud frame, metres). LAS/LAZ
    files are streamed in chunks (progress bar). munjer2025 expects one lidar frame in the
    sensor frame (pass-through box x 0..10, y -10..10, z -0.5..0 m).

    With the scanner's positions (--origin for one station, or --trajectory plus the points'
    time stamps for a mobile cloud) the circle fits of preset ours minimise the range errors
    along each point's ray, which removes the low DBH bias of a noisy mobile lidar.

    Writes the stems CSV (--out) and, on request, --geojson (WGS84 lon/lat when the CRS is
    known: --crs or the LAS header), --gpkg (native CRS) and --png (top view to scale). Every
    column: docs/outputs.md.

    Forestry products (preset ours): --profile (stem profiles CSV: diameter every 0.5 m up the
    visible stem, with std), --metrics (JSON: stems/ha, basal area m2/ha, quadratic mean
    diameter, DBH histogram, per-tree height and volume), --labels (LAS with a tree_id per
    point), --dtm (GeoTIFF terrain model). The CSV also gives diameter_std, the position
    covariance, where and why the DBH was measured (dbh_height, dbh_rule) and what heights are
    measured from (base).

    Example: stemmap stems plot.laz --out stems.csv --png stems.png

    Forestry: stemmap stems plot.laz --profile profile.csv --metrics metrics.json --labels trees.laz

    Terrain: stemmap stems plot.laz --dtm dtm.tif --crs EPSG:32633

    Tiles: stemmap stems tiles/ --out stems.csv --workers 2 --chunk-size 50 --buffer 5
    (a Dask cluster, one task per buffered chunk, resumable with --resume)

    Mobile: stemmap stems drive.laz --trajectory path.csv --sensor-offset 1.2,0

    One station: stemmap stems station.ply --origin 12.5,3.0
    """
    from dataclasses import replace

    import numpy as np

    from stemmap.cloud.export import (
        plot_stems,
        write_stems_csv,
        write_stems_geojson,
        write_stems_gpkg,
    )
    from stemmap.cloud.stems import StemConfig, detect_stems_file, get_preset
    from stemmap.engine import expand_inputs
    from stemmap.io.clouds import count_points
    from stemmap.io.geo import las_crs
    from stemmap.io.products import run_products

    with fail_on_stemmap_error():
        opts = EngineOptions(chunk_size, buffer, workers, scheduler, resume, work)
        engine = wants_engine(clouds, opts)
        in_paths = expand_inputs(clouds) if engine else [Path(clouds[0])]
    outputs = [out_csv, geojson, gpkg, png, report, profile, metrics, labels, dtm]
    with (
        fail_on_stemmap_error(),
        run_products("stems", inputs=[*in_paths, trajectory], outputs=outputs) as run,
        tempfile.TemporaryDirectory() as tmp,
    ):
        crs_given = crs is not None
        crs = checked_crs(crs) if crs_given else las_crs(in_paths[0])
        convention = _convention(units, up_axis, crs, engine=engine)
        crs, crs_note = output_crs(
            convention, crs, given=crs_given, georeferenced=any((geojson, gpkg, dtm))
        )
        if trajectory is not None and not convention.is_identity:
            raise ConfigError(
                "--trajectory cannot be combined with --units / --up-axis yet (the trajectory's "
                "units and axes are not known): convert the cloud to metres, z up first."
            )
        # (stderr: the --json object on stdout stays clean) said once the options are checked
        # and the input read (a non-LAS cloud is read whole before the first kernel call; a
        # LAS file's header checks are count_points'), so a bad input is reported instead
        notice = compile_notice("cloud", quiet=quiet)
        cfg = get_preset(preset)
        if not max_memory > 0:
            raise ConfigError(f"--max-memory must be > 0 GB, got {max_memory}.")
        if isinstance(cfg, StemConfig):
            cfg = replace(cfg, estimate_height=heights, max_memory=max_memory * 1e9)
        elif profile or metrics or labels or dtm:
            raise ConfigError(
                "--profile, --metrics, --labels and --dtm need preset ours (munjer2025 works "
                "on one lidar frame, not a plot)."
            )
        sensor = _sensor(origin, trajectory, time_field, time_offset, sensor_offset, convention)
        catalog = None
        if engine:
            if topic is not None:
                raise ConfigError("--topic applies to a bag, not to a tile catalog.")
            if profile or metrics or labels or dtm:
                raise ConfigError(
                    "--profile, --metrics, --labels and --dtm read the whole cloud: not "
                    "available for a tile catalog yet; run them per tile."
                )
            notice()
            result, _, catalog = run_catalog_stems(
                [str(p) for p in in_paths],
                cfg,
                opts,
                sensor,
                out_csv,
                quiet=quiet,
                unit_scale=convention.scale,
            )
            name = f"{len(catalog)} tiles"
        else:
            cloud = Path(clouds[0])
            grounds: list[GroundModel | None] = []
            name = cloud.name
            if cloud.suffix.lower() in (".las", ".laz"):  # streamed: header checks first
                count_points(cloud)
                notice()
            with progress(not quiet) as bar:
                task = bar.add_task(f"reading {cloud.name}", total=None)

                def tick(done: int, total: int) -> None:
                    notice()
                    bar.update(task, completed=done, total=total)

                result = detect_stems_file(
                    cloud,
                    cfg,
                    chunk_size=read_points,
                    on_chunk=tick,
                    sensor=sensor,
                    topic=topic,
                    on_ground=None if dtm is None else grounds.append,
                    convention=convention,
                )
        write_stems_csv(run.path(out_csv), result)
        # georeferenced products in the CRS's units: the stems are in metres (--units)
        geo = in_file_units(result, convention) if crs else result
        if geojson is not None:
            write_stems_geojson(run.path(geojson), geo, crs=crs)
        if gpkg is not None:
            write_stems_gpkg(run.path(gpkg), geo, crs=crs)
        sample = None  # every k-th point of the cloud, once read for the PNG or a hint
        fig_path = None if png is None else run.path(png)
        if report is not None and png is None:
            fig_path = Path(tmp) / "figure.png"
        if fig_path is not None:
            if catalog is not None:
                sample = catalog_sample(catalog)
            else:
                sample = _cloud_sample(cloud, read_points, topic, convention)
            bg = sample[:, :2]
            plot_stems(fig_path, result, background_xy=bg, title=name)
        if profile or metrics or labels:
            from stemmap.cli._stems_products import write_forestry_products

            write_forestry_products(
                cloud,
                result,
                read_points,
                topic,
                profile=None if profile is None else run.path(profile),
                metrics=None if metrics is None else run.path(metrics),
                labels=None if labels is None else run.path(labels),
                convention=convention,
            )
        if dtm is not None:
            from stemmap.cloud.dtm import require_terrain, write_dtm

            # the ground the detector measured heights from (no second pass over the file)
            ground = require_terrain(grounds[0], cloud)
            write_dtm(
                run.path(dtm),
                ground,
                crs,
                frame=cloud.name,
                unit=(convention.units, convention.scale) if crs else ("m", 1.0),
            )
        files = [str(p) for p in outputs if p is not None]
        med = float(np.nanmedian(result.diameter)) if len(result) else math.nan
        rows = [
            ("stems", fmt(len(result)), "rows of the CSV"),
            ("median DBH", fmt(med, " cm", 100, 1), "diameter"),
            ("method", result.method + (", along-ray fits" if sensor is not None else ""), ""),
            ("CRS", crs[:40] if crs else "none (local frame)", crs_note),
        ]
        rows.append(("input convention", convention.describe(), "--units / --up-axis"))
        said = height_reference(result)
        if said is not None:
            rows.append(("heights from", *said))
        if catalog is not None:
            rows.append(("tiles", fmt(len(catalog)), f"{fmt(catalog.n_points)} points"))
        if report is not None:
            assert fig_path is not None
            _stems_report(run.path(report), fig_path, result, Path(name), crs, rows, files)
        print_summary(
            f"stemmap stems: {name}", rows, None, files, as_json=as_json, quiet=quiet,
            payload={"n_stems": len(result), "median_dbh_m": med, "crs": crs,
                     "method": result.method, "units": convention.units,
                     "up_axis": convention.up_axis, **height_payload(result)},
        )  # fmt: skip
        if len(result) == 0:
            console.print(f"[yellow]warning:[/yellow] no stems found: {result.reason}.")
        hints = convention_hints(result, convention, user_set=units is not None)
        notes: list[str] = []
        if not hints and up_axis_wanted(result, convention, units):
            from stemmap.io.conventions import up_axis_hint

            if sample is None:  # one more streaming pass, only for a run of few (or no) stems
                sample = (
                    catalog_sample(catalog)
                    if catalog is not None
                    else _cloud_sample(cloud, read_points, topic, convention)
                )
            hint = up_axis_hint(sample, len(result))
            if hint is not None and catalog is not None:
                hint += CATALOG_UP_AXIS_NOTE
            if len(result):
                hints += [] if hint is None else [hint]
            else:  # the causes the run has evidence for, not a guess at the convention
                hints, notes = empty_result_notes(sample, hint, catalog=catalog is not None)
        doubt = base_warning(result)
        hints += [] if doubt is None else [doubt]
        for line in hints:
            console.print(f"[yellow]warning:[/yellow] {line}")
        for line in notes:
            console.print(f"note: {line}")


#: Median DBH (m) above which a run's stems are more likely a cloud in feet than real trees:
#: feet make every diameter x3.28 (the real plots here: 0.17 m and 0.30 m median in metres,
#: 0.82 m and 0.97 m read as feet). A warning, not a refusal: old-growth plots can exceed it.
FEET_SUSPECT_MEDIAN_DBH = 0.6


def _convention(units: str | None, up_axis: str, crs: str | None, *, engine: bool) -> Any:
    """The input convention of the options; ConfigError for a CRS whose unit is not the
    metre when --units is not given (its coordinates would be measured as metres), for
    --units that contradict the CRS's unit, and for --up-axis on a tile catalog."""
    from stemmap.io.conventions import CloudConvention, crs_unit, unit_for_factor

    convention = CloudConvention(units or "m", up_axis)
    unit = crs_unit(crs)
    shown = crs if len(crs or "") < 40 else "given"
    if unit is not None and units is None and abs(unit[1] - 1.0) > 1e-9:
        name = unit_for_factor(unit[1])
        hint = f"pass --units {name}" if name else "convert the cloud to metres"
        raise ConfigError(
            f"the cloud's CRS ({shown}) measures in {unit[0]} ({unit[1]:g} m), but stemmap "
            f"measures stems in metres: {hint} (the results are then in metres)."
        )
    # ft against us-ft is 2 ppm (a diameter error of 0.0002 mm): only a real contradiction
    if unit is not None and units is not None and abs(unit[1] / convention.scale - 1) > 0.01:
        raise ConfigError(
            f"--units {units} contradicts the cloud's CRS ({shown}), which measures in "
            f"{unit[0]} ({unit[1]:g} m): pass the CRS's unit, or --crs with the CRS the "
            "coordinates are really in."
        )
    if engine and up_axis != "z":
        raise ConfigError(
            f"--up-axis {up_axis} applies to one cloud, not to a tile catalog: tiles are cut "
            "on their x, y, which must be horizontal. Turn the tiles z up first (PDAL: "
            "filters.transformation with matrix '1 0 0 0 0 0 -1 0 0 1 0 0 0 0 0 1' for y up), "
            "or run each file on its own with --up-axis."
        )
    return convention


def output_crs(
    convention: Any, crs: str | None, *, given: bool, georeferenced: bool
) -> tuple[str | None, str]:
    """The CRS the products are written in, and a note for the summary.

    A CRS describes the file's x, y (horizontal). With ``--up-axis y`` (or x) the file's y is
    vertical, so a LAS header's CRS cannot describe the turned frame: it is not used (the
    products are declared a local frame) unless ``--crs`` is given, which then names the CRS
    of the turned frame's x, y. With ``--units`` the georeferenced products are written in the
    CRS's own units (:func:`in_file_units`); the CSV stays in metres.
    """
    if convention.up_axis != "z" and crs is not None and not given:
        note = (
            f"the LAS header's {crs[:40]} is not used: it describes the file's x, y, and the "
            f"file's {convention.up_axis} is up (pass --crs for the turned frame's CRS)"
        )
        if georeferenced:
            from stemmap.cli._common import console

            console.print(f"[yellow]warning:[/yellow] {note}; the products are in a local frame.")
        return None, note
    if crs is not None and convention.scale != 1.0:
        return crs, f"GeoJSON / GPKG / DTM in its units ({convention.units}); CSV in metres"
    return crs, ""


def in_file_units(result: Any, convention: Any) -> Any:
    """``result`` with its positions back in the file's (the CRS's) units: the georeferenced
    products' geometry (attributes such as diameter and z stay in metres)."""
    from dataclasses import replace

    if convention.scale == 1.0:
        return result
    return replace(result, xy=result.xy / convention.scale)


def _cloud_sample(cloud: Path, read_points: int, topic: str | None, convention: Any) -> Any:
    """Every k-th point (about 200 000) of the whole file, converted: one more streaming pass
    (the size of a non-LAS file is known only once it is read, as one chunk)."""
    import numpy as np

    from stemmap.io.clouds import count_points, iter_cloud_chunks

    total = count_points(cloud)
    return np.concatenate(
        [
            c.xyz[:: max(1, (total or len(c)) // 200_000)]
            for c in iter_cloud_chunks(cloud, read_points, topic=topic, convention=convention)
        ]
    )


#: A run of at most this many stems, without --up-axis, has its cloud's shape checked for
#: another up axis (:func:`stemmap.io.conventions.up_axis_hint`): single trees, and plots read
#: with the wrong axis (a simulated Y-up plot gave 3 stems, the real pine_plot 0).
UP_AXIS_CHECK_MAX_STEMS = 5


def up_axis_wanted(result: Any, convention: Any, units: str | None) -> bool:
    """Whether the cloud's shape is checked for another up axis (a run of at most
    :data:`UP_AXIS_CHECK_MAX_STEMS` stems, none included, no --units / --up-axis given)."""
    return units is None and convention.is_identity and len(result) <= UP_AXIS_CHECK_MAX_STEMS


def convention_hints(result: Any, convention: Any, *, user_set: bool) -> list[str]:
    """Warnings for a run whose result suggests the wrong units or up axis (none when the
    user set --units or --up-axis)."""
    import numpy as np

    if user_set or not convention.is_identity or len(result) == 0:
        return []  # an empty result: the evidence of its cloud (empty_result_notes)
    med = float(np.nanmedian(result.diameter))
    if med > FEET_SUSPECT_MEDIAN_DBH:
        return [
            f"the median DBH is {med:.2f} m, large for a plot: if the cloud is in feet, pass "
            "--units ft (or us-ft); a cloud in feet reads every diameter x3.28. If it is a "
            "slice or a tree whose y points up, pass --up-axis y."
        ]
    return []


def _stems_report(
    path: Path, fig: Path, result: Any, cloud: Path, crs: str | None, rows: Any, files: Any
) -> None:
    """report.html of a stems run: the figure, DBH histogram, summary and per-stem table."""
    import numpy as np

    from stemmap.cloud.export import STEM_CSV_COLUMNS
    from stemmap.viz.report import write_report

    metrics: dict[str, Any] = {
        "n_stems": len(result),
        "median_dbh_m": float(np.nanmedian(result.diameter)) if len(result) else None,
        "method": result.method,
        "crs": crs,
        "point_spacing_m": float(result.spacing) if math.isfinite(result.spacing) else None,
    }
    cols = [
        c
        for c in STEM_CSV_COLUMNS
        if c not in ("id", "method", "base")
        and hasattr(result, c)
        and np.asarray(getattr(result, c)).dtype.kind in "biuf"
    ]
    table = [
        [k, round(float(result.xy[k, 0]), 3), round(float(result.xy[k, 1]), 3)]
        + [round(float(getattr(result, c)[k]), 4) for c in cols if c not in ("x", "y")]
        for k in range(len(result))
    ]
    header = ["id", "x", "y", *[c for c in cols if c not in ("x", "y")]]
    write_report(
        path,
        title=f"stemmap stems: {cloud.name}",
        headline=", ".join(f"{r[0]} {r[1]}" for r in rows),
        metrics=metrics,
        figure_png=fig.read_bytes(),
        diameters=result.diameter,
        table_header=header,
        table_rows=table,
        parameters={"cloud": str(cloud), "method": result.method, "crs": crs},
        warnings=[] if crs else ["no CRS: coordinates are the cloud's local metres."],
        files=[str(f) for f in files],
    )


def register(app: typer.Typer) -> None:
    app.command("stems")(stems)
