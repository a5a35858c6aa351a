"""Simulator: stands, 2D scanner, drives with odometry -- every input with ground truth.

See docs/algorithms/sim-eval.md for the models and the decisions behind them.
"""

from stemmap.sim.forest import (
    Stand,
    clustered_stand,
    random_stand,
    row_stand,
    sample_dbh,
    stand_from_spec,
)
from stemmap.sim.motion_sensors import (
    ODOMETRY_PRESETS,
    Gnss,
    GnssNoise,
    Odometry,
    OdometryNoise,
    RelativeOdometry,
    VisualOdometryNoise,
)
from stemmap.sim.observations import (
    oracle_observations,
    returns_per_tree,
    trees_in_sensor_frame,
)
from stemmap.sim.outline import trunk_outline
from stemmap.sim.paths import (
    clear_corridor,
    lawnmower_path,
    loop_path,
    s_curve_path,
    straight_path,
)
from stemmap.sim.scanner import (
    HIT_CLUTTER,
    HIT_NONE,
    SCANNER_PRESETS,
    ScannerModel,
    cast_rays,
    cast_scans,
    scanner_preset,
    simulate_scan,
    simulate_scans,
)
from stemmap.sim.stand_features import (
    CLUTTER_KINDS,
    add_clutter,
    add_understory,
    make_trunks_noncircular,
)
from stemmap.sim.trajectory import SimRun, simulate_run
from stemmap.sim.unicycle import compose_poses, integrate_unicycle, relative_poses

__all__ = [
    "CLUTTER_KINDS",
    "HIT_CLUTTER",
    "HIT_NONE",
    "ODOMETRY_PRESETS",
    "SCANNER_PRESETS",
    "Gnss",
    "GnssNoise",
    "Odometry",
    "OdometryNoise",
    "RelativeOdometry",
    "ScannerModel",
    "SimRun",
    "Stand",
    "VisualOdometryNoise",
    "add_clutter",
    "add_understory",
    "cast_rays",
    "cast_scans",
    "clear_corridor",
    "clustered_stand",
    "compose_poses",
    "integrate_unicycle",
    "lawnmower_path",
    "loop_path",
    "make_trunks_noncircular",
    "oracle_observations",
    "random_stand",
    "relative_poses",
    "returns_per_tree",
    "row_stand",
    "s_curve_path",
    "sample_dbh",
    "scanner_preset",
    "simulate_run",
    "simulate_scan",
    "simulate_scans",
    "stand_from_spec",
    "straight_path",
    "trees_in_sensor_frame",
    "trunk_outline",
]
