"""``stemmap detect``: trunks in 2D laser scans (NPZ, CSV, ROS1/ROS2 bags) -> observations CSV."""

from __future__ import annotations

import csv
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from stemmap.cli._common import QuietFlag, console, fail_on_stemmap_error, out, progress
from stemmap.cli._multilog import SchedulerOption, WorkersOption, run_many_logs, wants_logs
from stemmap.cli._summary import announce_compile
from stemmap.cli._validate import bounded
from stemmap.errors import ConfigError, InputError
from stemmap.scan.config import ARC_OPTIONS


class NoiseScale(StrEnum):
    """The batch range-noise estimate's statistic (``batch_noise_scale``)."""

    mad = "mad"
    biweight = "biweight"


__all__ = ["detect", "register"]

#: Scans per detect_batch call: large enough to amortise numpy overhead, small enough for a
#: responsive progress bar.
_CHUNK = 2000
#: Show a progress bar from this many scans on.
_PROGRESS_MIN_SCANS = 5000


def detect(
    scans: Annotated[
        list[Path],
        typer.Argument(
            help="Scan file: .npz, .csv, ROS1 .bag or ROS2 bag (folder/.db3/.mcap). Several "
            "logs (files, a folder, a glob, a .txt list) run one Dask task per log."
        ),
    ],
    out_path: Annotated[
        Path,
        typer.Option(
            "--out",
            "-o",
            help="Observations CSV to write (one row per trunk); with several logs a folder: "
            "OUT/LOG/observations.csv per log and OUT/summary.csv.",
        ),
    ],
    preset: Annotated[
        str,
        typer.Option(help="Detector preset: stemmap, zheng2012, xue2018, visual_lidar2023."),
    ] = "stemmap",
    topic: Annotated[
        str | None, typer.Option(help="LaserScan topic of a bag (default: the only one).")
    ] = None,
    imu_topic: Annotated[
        str | None,
        typer.Option(
            help="sensor_msgs/Imu topic of the same bag: its roll and pitch (interpolated at "
            "each scan time) project the tilted scan onto the horizontal before detection "
            "(Zheng 2012 eq. 1 with --preset zheng2012, the exact rotation otherwise). The IMU "
            "axes must be the scanner's (an AHRS fixed on the scanner, as in Zheng 2012)."
        ),
    ] = None,
    fit: Annotated[
        str | None,
        typer.Option(
            help="Override the preset's circle fit (kasa, fletcher_reeves, ours, ...) "
            "[default: the preset's: stemmap ours, zheng2012 fletcher_reeves, xue2018 "
            "chord_width, visual_lidar2023 kasa]."
        ),
    ] = None,
    sigma: Annotated[
        float | None,
        typer.Option(
            help="Override the sensor range noise (1 sigma), metres [default: the preset's, "
            "0.01 m for every preset].",
            callback=bounded("--sigma", gt=0),
        ),
    ] = None,
    sigma_from_scan: Annotated[
        bool | None,
        typer.Option(
            "--sigma-from-scan/--no-sigma-from-scan",
            help="Estimate each scan's range noise from its own returns (robust scale of the "
            "second differences of neighbouring ranges inside continuous surfaces, run ends "
            "left out) and use it wherever it exceeds the configured sensor noise (--sigma). "
            "Helps noisy scanners; default: the preset's setting (on for stemmap, off for "
            "the paper presets).",
        ),
    ] = None,
    noise_batch: Annotated[
        float | None,
        typer.Option(
            "--noise-batch",
            metavar="FACTOR",
            help="Scans too sparse for their own range-noise estimate (a few trunks at 0.5-1 "
            "deg) take the estimate over every scan of their batch of 2000 (a stretch of the "
            "file) where it is at least FACTOR x --sigma: a scanner clearly noisier than "
            "configured is then not rejected for it (scan_noise_batch, with --sigma-from-scan; "
            "e.g. 2.5). Off by default (docs/algorithms/scan-detection.md, 'Range noise on "
            "sparse scans').",
            callback=bounded("--noise-batch", ge=1),
        ),
    ] = None,
    noise_batch_scale: Annotated[
        NoiseScale | None,
        typer.Option(
            "--noise-batch-scale",
            help="The statistic of the range-noise estimate over every scan of a batch, which a "
            "scan too sparse for its own takes (the fit's noise with --footprint, the step "
            "split's threshold, --noise-batch): mad (1.4826 x the median absolute deviation) "
            "or biweight (the biweight midvariance: as robust, a quarter less sampling spread "
            "on the few tens of triples of a sparse batch; batch_noise_scale). Default: the "
            "preset's (biweight in stemmap since Dec 5, grid 80; mad in the paper presets; "
            "docs/algorithms/scan-detection.md, 'The batch's noise from few triples').",
        ),
    ] = None,
    step_split: Annotated[
        bool | None,
        typer.Option(
            "--step-split/--no-step-split",
            help="Cut a candidate that fails the RMS test at its largest range step when the "
            "step is beyond the noise (read against every scan's pooled noise where a scan "
            "has no estimate of its own): a thin stem whose segment runs on into a branch "
            "behind it. On in the stemmap preset since Dec 5: the leave-one-dataset-out "
            "choice on real trunk geometry for every held-out dataset (TreeLS plot held out: "
            "recall 0.90 -> 0.95), at ~0.92x the speed (step_split, step_noise_pool='batch'; "
            "docs/algorithms/scan-detection.md, 'Step split, fold by fold'). Default: the "
            "preset's (off in the paper presets, which have no RMS test for it to act on).",
        ),
    ] = None,
    arcs: Annotated[
        bool | None,
        typer.Option(
            "--arcs/--no-arcs",
            help="Fit each candidate's largest consistent arc: a trunk whose returns run on "
            "into a branch stub, fillet or neighbouring stem is measured on its own arc "
            "(arc_refit, consensus at 2 robust scales, an accepted fit replaced when its RMS "
            "exceeds 3x the arc's), kept only when no return lies behind the circle's tangent "
            "range and its residuals are the range noise (chi-square), which keeps faces of "
            "lobed rocks out; an arc of 4 returns counts where a range step sets it off "
            "(arc_short_steps). On in the stemmap preset since the fifteenth round "
            "(docs/algorithms/scan-detection.md); --arcs turns it on for a paper preset, "
            "--no-arcs off. Default: the preset's setting.",
        ),
    ] = None,
    footprint: Annotated[
        float | None,
        typer.Option(
            help="Beam footprint of a nearest-return (first-echo) scanner, degrees: its "
            "returns are moved to the footprint side nearest the trunk (corrects wide trunks) "
            "[default: 0, none: an averaging scanner such as a SICK LMS2xx or the simulator]. "
            "With it the stemmap preset's fits also weight by the measured noise "
            "(--fit-noise-floor), a run of end returns off the circle (a branch leaving the "
            "flank) goes when the fit fails the chi-square test against that noise, and a "
            "re-fitted piece drops the return at its cut end (since Dec 5, grid 80: lidR "
            "0.5 deg DBH RMSE 4.20 -> 1.75 cm; docs/algorithms/scan-detection.md, 'Grid 80 "
            "is the stemmap preset').",
            callback=bounded("--footprint", ge=0, lt=180),
        ),
    ] = None,
    fit_noise_floor: Annotated[
        float | None,
        typer.Option(
            "--fit-noise-floor",
            metavar="METRES",
            help="With --footprint (a first-echo scanner): the circle fits weight the returns "
            "by the range noise measured on the scans plus the footprint's range step, at "
            "least METRES and at most --sigma, while the plausibility tests keep --sigma; a "
            "stem whose returns scatter by millimetres then follows them rather than one edge "
            "return on a stub or twig. 0 = off (the fits use --sigma). Default: the preset's "
            "(0.003 in stemmap since Dec 5: the leave-one-dataset-out choice on real trunk "
            "geometry, lidR held out recall 0.92 -> 1.00; 0 in the paper presets). No effect "
            "without --footprint (docs/algorithms/scan-detection.md, 'The fit's measured "
            "noise, the default').",
            callback=bounded("--fit-noise-floor", ge=0),
        ),
    ] = None,
    edge_hit: Annotated[
        tuple[float, float] | None,
        typer.Option(
            "--edge-hit",
            metavar="MIN MAX",
            help="Return threshold of an averaging (SICK-class) scanner, the share of its "
            "footprint that must hit for a beam to return, assumed to lie in [MIN, MAX]: 0.5 "
            "0.5 = half the footprint (the default, every preset), 0 0 = any part, 0 0.5 = "
            "unknown (the tangent prior widened by half a footprint). A real SICK LMS200 "
            "measured 0.25-0.38 (Victoria Park, 2-15 m): 0.25 0.38, with --edge-hit-window. "
            "Other values are not the default: on real trunk geometry scanned at the measured "
            "0.3, 0.25-0.38 scores below half in three of four leave-one-dataset-out folds "
            "(on the simulator's circles, whose SICK returns at 0.3 since Dec 6, it removes a "
            "+0.2 cm DBH bias; docs/algorithms/scan-detection.md, 'One return threshold for "
            "the simulator and the benchmark').",
        ),
    ] = None,
    edge_hit_window: Annotated[
        bool | None,
        typer.Option(
            "--edge-hit-window/--no-edge-hit-window",
            help="With --edge-hit MIN below 0.5 (an averaging scanner that returns when less "
            "than half its footprint hits): also model the range of a trunk's two edge returns "
            "as the mean over the part of the footprint on the trunk, at least MIN of it. An "
            "edge beam that grazes the trunk with a thin sliver reports the sliver's range, "
            "nearer than the half-footprint average the default assumes; without this the fit "
            "reads that nearer range as a wider trunk (+0.6 to +1.1 cm on 40-60 cm trunks at "
            "10-14 m on an any-hit scanner). Use it whenever --edge-hit MIN is below 0.5, e.g. "
            "--edge-hit 0.25 0.38 --edge-hit-window for a SICK LMS200 (the share measured on "
            "a real one, Victoria Park, 2-15 m). No effect at MIN 0.5 (the default threshold). "
            "Off by default, as any threshold below half is (docs/algorithms/scan-detection.md,"
            " 'The averaging edge bias against textbook Kasa', 'The measured LMS200 threshold "
            "for every averaging model').",
        ),
    ] = None,
    rejected: Annotated[
        Path | None,
        typer.Option(
            "--rejected",
            help="Also write the rejected trunk candidates to this CSV, each with the test "
            "that dropped it (reason column; split / arc: cut into pieces that were kept).",
        ),
    ] = None,
    range_unit: Annotated[
        str | None,
        typer.Option(
            help="Unit of the ranges: m, cm, mm, ft or us-ft, converted to metres [default: "
            "m; scans whose median return is beyond 500 m are refused without it]."
        ),
    ] = None,
    quiet: QuietFlag = False,
    workers: WorkersOption = None,
    scheduler: SchedulerOption = None,
) -> None:
    """Detect the trunks in every 2D laser scan: one CSV row per trunk per scan.

    Columns scan_index, time_s, x, y, diameter, radius_std, n_points, ... (docs/outputs.md).
    Coordinates are in the sensor frame (metres). A damaged frame is reported and skipped;
    ``scan_index`` is the frame's position in the file, so skipped frames leave gaps.

    Example: stemmap detect run.npz --out stems.csv --preset stemmap

    --rejected FILE lists every candidate that failed the detector's tests with the test it
    failed (reason: width, depth, straight, rms, radius_width_ratio, ...; docs/cli.md); a
    merged candidate whose re-fitted pieces were kept has reason split (or arc), the test in
    failed_test and the pieces' count in pieces / pieces_accepted.

    Example: stemmap detect logs/ --out det --workers 2  (one folder per log + summary.csv)

    Example: stemmap detect crane.bag --out stems.csv --imu-topic /imu  (tilted scanner)
    """
    if wants_logs(scans, workers, scheduler):
        return run_many_logs("detect", dict(locals()))
    scan = scans[0]
    from stemmap.io.maps import write_observations_csv
    from stemmap.io.products import run_products
    from stemmap.io.scans import SkippedFrame, read_scans
    from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
    from stemmap.scan.plausibility import PIECE_REASONS
    from stemmap.types import ScanBatch, StemObservations

    with (
        fail_on_stemmap_error(),
        run_products("detect", inputs=[scan], outputs=[out_path, rejected]) as run,
    ):
        overrides: dict[str, object] = {}
        if fit is not None:
            overrides["fit_method"] = fit
        if sigma is not None:
            overrides["sigma"] = sigma
        if footprint is not None:
            overrides["beam_footprint_deg"] = footprint
        if fit_noise_floor is not None:
            overrides["fit_noise_floor"] = fit_noise_floor
        if edge_hit is not None:
            overrides["edge_hit_min"], overrides["edge_hit_max"] = map(float, edge_hit)
        if edge_hit_window is not None:
            overrides["edge_hit_window"] = edge_hit_window
        if sigma_from_scan is not None:
            overrides["sigma_from_scan"] = sigma_from_scan
        if noise_batch is not None:
            overrides["scan_noise_batch"] = noise_batch
        if noise_batch_scale is not None:
            overrides["batch_noise_scale"] = noise_batch_scale.value
        if step_split:
            overrides["step_split"] = True
            overrides["step_noise_pool"] = "batch"
        elif step_split is not None:
            overrides["step_split"] = False
        if arcs:
            overrides.update(ARC_OPTIONS)
        elif arcs is not None:
            overrides["arc_refit"] = False
        detector = ScanTrunkDetector(DetectorConfig.preset(preset, **overrides))
        if imu_topic is not None and rejected is not None:
            raise ConfigError(
                "--rejected lists candidates of the untilted scans; it cannot be combined with "
                "--imu-topic yet. Run once without --imu-topic for the rejected list."
            )
        skipped: list[SkippedFrame] = []
        batch = read_scans(scan, topic=topic, skipped=skipped, range_unit=range_unit)
        roll, pitch = _scan_attitude(scan, imu_topic, batch.times)
        # the first run compiles the detector for minutes before the progress bar starts
        # (said once every input is read: a bad input is reported, not a compile first)
        announce_compile("scan", quiet=quiet)
        for sk in skipped:
            console.print(
                f"[yellow]skipped frame {sk.frame_index}[/yellow] (t={sk.time:.3f} s): {sk.reason}"
            )
        # file position of every kept frame (read_scans drops the skipped ones)
        n_total = len(batch) + len(skipped)
        dropped = {sk.frame_index for sk in skipped}
        file_index = np.array([i for i in range(n_total) if i not in dropped], dtype=np.int64)
        if file_index.shape[0] != len(batch):  # skipped indices outside 0..n_total-1
            file_index = np.arange(len(batch), dtype=np.int64)
        parts: list[StemObservations] = []
        rejected_parts: list[dict[str, Any]] = []
        show = not quiet and len(batch) >= _PROGRESS_MIN_SCANS
        with progress(show) as bar:
            task = bar.add_task("detecting trunks", total=len(batch))
            for a in range(0, len(batch), _CHUNK):
                b = min(a + _CHUNK, len(batch))
                chunk = ScanBatch(
                    batch.ranges[a:b],
                    batch.times[a:b],
                    batch.angle_min,
                    batch.angle_increment,
                    batch.range_min,
                    batch.range_max,
                    batch.frame,
                )
                if rejected is not None:  # (no IMU: refused above)
                    obs, rej = detector.detect_with_rejected(chunk)
                    local = rej["scan_index"]
                    rej["time"] = chunk.times[local]
                    rej["scan_index"] = file_index[a + local]
                    rejected_parts.append(rej)
                else:
                    obs = detector.detect_batch(
                        chunk,
                        roll=None if roll is None else roll[a:b],
                        pitch=None if pitch is None else pitch[a:b],
                    )
                parts.append(
                    StemObservations(
                        centers=obs.centers,
                        radii=obs.radii,
                        covs=obs.covs,
                        n_points=obs.n_points,
                        arc_deg=obs.arc_deg,
                        widths=obs.widths,
                        quality=obs.quality,
                        index=file_index[a + obs.index],
                        times=obs.times,
                        source=obs.source,
                        frame=obs.frame,
                    )
                )
                bar.advance(task, b - a)
        result = StemObservations.concatenate(parts)
        if len(result) == 0:
            result = StemObservations.empty(source=detector.source, frame=batch.frame)
        write_observations_csv(run.path(out_path), result)
        if rejected is not None:
            n_rejected = _write_rejected_csv(run.path(rejected), rejected_parts)
            n_pieces = sum(sum(r in PIECE_REASONS for r in p["reason"]) for p in rejected_parts)
    if not quiet:
        n_with = len(np.unique(result.index)) if len(result) else 0
        out.print(
            f"{len(result)} trunk observations in {n_with} of {len(batch)} scans "
            f"({len(skipped)} skipped) -> {out_path}  [preset {preset}, fit "
            f"{detector.config.fit_method}]",
            markup=False,
        )
        if rejected is not None:
            kept = f" ({n_pieces} of them re-fitted as pieces that were kept)" if n_pieces else ""
            out.print(f"{n_rejected} rejected candidates{kept} -> {rejected}", markup=False)


#: IMU samples may end this long before the first / after the last scan (s): an IMU at
#: >= 10 Hz started with the scanner covers its scans to within a sample period or two.
_IMU_MAX_GAP_S = 0.5


def _scan_attitude(
    scan: Path, imu_topic: str | None, times: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Roll and pitch (rad) of every scan from the bag's IMU topic (None without one).

    Linear interpolation of the IMU's roll and pitch at the scan times (``ImuLog.tilt_at``);
    scans more than :data:`_IMU_MAX_GAP_S` outside the IMU's time span are an error, not a
    silently held attitude.
    """
    if imu_topic is None:
        return None, None
    from stemmap.io.rosbag import is_bag, read_imu

    if not is_bag(scan):
        raise ConfigError(
            f"--imu-topic reads a sensor_msgs/Imu topic from a ROS bag; {scan} is not a bag."
        )
    imu = read_imu(scan, imu_topic)
    if len(times):
        lo, hi = float(imu.times[0]), float(imu.times[-1])
        t0, t1 = float(np.min(times)), float(np.max(times))
        if t0 < lo - _IMU_MAX_GAP_S or t1 > hi + _IMU_MAX_GAP_S:
            raise InputError(
                f"IMU topic {imu_topic!r} of {scan} covers t = {lo:.3f}..{hi:.3f} s but the "
                f"scans span {t0:.3f}..{t1:.3f} s; the attitude of scans outside it is unknown. "
                "Check the topic, or cut the scans to the IMU's time span."
            )
    return imu.tilt_at(times)


#: Columns of the ``--rejected`` CSV (stemmap.scan.plausibility.rejected_candidates).
_REJECTED_COLUMNS = (
    "scan_index",
    "time",
    "reason",
    "n_points",
    "bearing_deg",
    "range",
    "width",
    "partial",
    "x",
    "y",
    "radius",
    "rms",
    "sigma",
    "failed_test",
    "pieces",
    "pieces_accepted",
)


def _write_rejected_csv(path: Path, parts: list[dict[str, Any]]) -> int:
    """Write the rejected candidates (one row each, :data:`_REJECTED_COLUMNS`); NaN = not
    fitted (dropped by a segment filter). Returns the row count."""
    from stemmap.errors import InputError
    from stemmap.io._util import fmt_float

    n = 0
    try:
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(_REJECTED_COLUMNS)
            for part in parts:
                cols = [part[c] for c in _REJECTED_COLUMNS]
                for row in zip(*cols, strict=True):
                    # floats exactly as the observations CSV writes them (fmt_float): a
                    # 6-digit format turned epoch times (1.7e9 s) into whole 1000 s steps
                    w.writerow(
                        [
                            fmt_float(float(v))
                            if isinstance(v, float | np.floating)
                            else (int(v) if isinstance(v, np.bool_ | bool) else v)
                            for v in row
                        ]
                    )
                    n += 1
    except OSError as exc:
        raise InputError(f"cannot write the rejected candidates to {path}: {exc}.") from exc
    return n


def register(app: typer.Typer) -> None:
    """Add ``detect`` to the ``stemmap`` app."""
    app.command("detect")(detect)
