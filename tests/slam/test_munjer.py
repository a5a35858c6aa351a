"""Munjer et al. 2025 end to end on a simulated Munjer-like drive (sim/munjer.py): EB-LiDAR,
DAIM (boxes from the segmentation detector, never truth) and stemmap's own cloud detector, each
through FastSLAM (100 particles) + the Kalman refinement, scored as the paper's Table 2.

One lap of seed 1 (148 lidar frames at 10 Hz, 4 m/s, 13 trees, 3 bushes); the numbers quoted
in the tolerances are from ``python benchmarks/munjer2025.py`` (docs/algorithms/slam-frontends.md).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from stemmap.cloud.filters import pass_through
from stemmap.cloud.munjer import MunjerConfig
from stemmap.errors import ConfigError, InputError
from stemmap.eval.detection import DetectionMetrics
from stemmap.eval.maps import MapMetrics
from stemmap.sim.motion_sensors import OdometryNoise
from stemmap.sim.munjer import D435_DEPTH_K, MunjerDrive, simulate_munjer_drive
from stemmap.sim.odometry_model import increment_error_moments
from stemmap.slam.base import dead_reckoning
from stemmap.slam.motion import rollout
from stemmap.slam.munjer import (
    MunjerMapConfig,
    accumulate_frames,
    controls_from_trajectory,
    daim_observations,
    eb_lidar_observations,
    map_munjer,
    munjer_problem,
    ours_lidar_observations,
)
from stemmap.types import StemObservations, Trajectory
from stemmap.vision.detector import SegmentationDetector


@pytest.fixture(scope="module")
def drive() -> MunjerDrive:
    return simulate_munjer_drive(rng=1, camera_every=2)


def _map(
    d: MunjerDrive, obs: StemObservations, times: np.ndarray | None = None
) -> tuple[DetectionMetrics, MapMetrics]:
    t = d.times if times is None else times
    p0 = (float(d.poses[0, 0]), float(d.poses[0, 1]), float(d.poses[0, 2]))
    problem = munjer_problem(obs, t, d.controls(), d.motion_model(), initial_pose=p0)
    return d.score(map_munjer(problem, MunjerMapConfig(seed=1)).stem_map)


def test_lidar_and_camera_see_the_same_stand(drive: MunjerDrive) -> None:
    """Both renderers use one stand: lidar returns labelled tree k lie on tree k's cylinder,
    depth pixels labelled tree k back-project onto it (exact up to the sensors' noise)."""
    st = drive.stand2d
    f = 20
    fr, pose = drive.frames[f], drive.poses[f]
    lab = fr.fields["label"]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    w = fr.xyz[:, :2] @ np.array([[c, s], [-s, c]]) + pose[:2]
    on = lab >= 0
    d = np.hypot(*(w[on] - st.trees_xy[lab[on]]).T) - st.radii[lab[on]]
    assert on.sum() > 100 and np.median(np.abs(d)) < 0.03  # VLP-16 noise: 3 cm
    k = int(np.flatnonzero(drive.camera_frames == f)[0])
    from stemmap.vision.depth import depth_to_points

    ll = drive.image_labels[k]
    ids = np.unique(ll[ll >= 0])
    t = int(ids[np.argmin([np.nanmedian(drive.depths[k][ll == i]) for i in ids])])  # nearest
    ys, xs = np.nonzero(ll == t)
    box = [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
    only_t = np.where(ll == t, drive.depths[k], np.nan)  # the tree's own pixels
    pc = depth_to_points(only_t, drive.rig.camera, box)
    body = drive.rig.laser_to_camera.inverse().apply(pc)[:, :2]
    wb = body @ np.array([[c, s], [-s, c]]) + pose[:2]
    dd = np.hypot(*(wb - st.trees_xy[t]).T) - st.radii[t]
    # D435 depth noise sigma = k z^2 (radial spread; the median |error| is ~0.7 sigma)
    z = float(np.nanmedian(only_t))
    assert np.median(np.abs(dd)) < 0.01 + D435_DEPTH_K * z**2


def test_eb_lidar_eccentricity_reading(drive: MunjerDrive) -> None:
    """Why EB-LiDAR recall collapsed: over the two largest eigenvalues a 16-beam trunk cluster
    has e ~ 1.4-3.5 (its 0.5 m band against its width), so the window [10, 20] keeps nothing;
    largest over smallest (a partial trunk is a thin curved sheet) keeps trunks."""
    old = eb_lidar_observations(
        drive.frames, drive.times, MunjerConfig(eccentricity_axes="largest")
    )
    new = eb_lidar_observations(drive.frames, drive.times)
    # measured 3 vs 68 detections on this lap (0 trees in the "largest" maps of 3 seeds)
    assert len(new) >= 40 and len(old) < 0.1 * len(new)


def test_every_tree_enters_the_pass_through_box(drive: MunjerDrive) -> None:
    """Scoring protocol: the paper scores the trees of the area the robot drove through; the
    benchmark scores all trees, which is the same only if every tree enters EB-LiDAR's box
    (Table 1: x in (0, 10), |y| < 10 m) in some frame. The box test itself is checked on a tree
    placed 30 m off the stand, which never enters it."""
    inside = drive.trees_in_box()
    assert inside.shape == (drive.stand2d.n_trees,) and inside.all()
    far = replace(drive, stand2d=replace(drive.stand2d, trees_xy=drive.stand2d.trees_xy + 30.0))
    assert not far.trees_in_box().any()
    assert far.trees_in_box(None, None).all()


def test_trees_visible_counts_box_returns(drive: MunjerDrive) -> None:
    """The "enough points" scoring view: a tree counts when >= 20 of its lidar returns fall
    inside the pass-through box in some frame (the frames' hit labels). Every such tree is in
    the box; on this lap nearly all are (measured 13 of 13; seed 0 has 2 of 12 with <= 8
    returns, 10-11 m from the path); nothing is visible through an empty box or with an
    unreachable point count, and a lower count admits at least the same trees."""
    vis = drive.trees_visible()
    assert vis.shape == (drive.stand2d.n_trees,) and vis.sum() >= drive.stand2d.n_trees - 1
    assert (vis <= drive.trees_visible(min_points=5)).all()
    assert not drive.trees_visible(min_points=10**6).any()
    assert not drive.trees_visible(box_x=(100.0, 101.0)).any()


def test_eb_lidar_ring_gap_limits_range() -> None:
    """Why EB-LiDAR misses far trunks on a VLP-16: rings are 2 degrees apart, so beyond
    eps / tan(2 deg) = 7.2 m two rings on a trunk are more than DBSCAN's eps = 0.25 m apart and
    every cluster is one ring -- never 20 points on a 0.3 m trunk, and a flat arc besides. A
    single frame of one noise-free 0.3 m trunk (sensor 0.8 m up): found at 3 m (145 points in
    the box, e = 19.8), no DBSCAN cluster at all at 8 m (22 points in 2 rings 0.28 m apart)."""
    from stemmap.cloud.munjer import detect_stems_munjer
    from stemmap.sim.lidar import Stand3D, lidar_preset, simulate_mobile

    lidar = lidar_preset("vlp16", range_noise=0.0)
    found = {}
    for r in (3.0, 8.0):
        st = Stand3D(np.array([[r, 0.0]]), np.array([0.3]), np.array([8.0]), np.zeros((1, 2)),
                     np.zeros(1), ground=(0.0, 0.0, 0.0))  # fmt: skip
        mob = simulate_mobile(
            st, np.array([[0.0, 0.0], [0.0, 0.01]]), lidar, height=0.8, yaws=[0, 0], rng=0
        )
        frame = mob.frames[0]
        found[r] = len(detect_stems_munjer(frame.xyz))
    assert found == {3.0: 1, 8.0: 0}


def test_eb_lidar_ring_gap_with_the_hires_sensor() -> None:
    """The Puck Hi-Res (rings 1.33 deg apart) moves the ring-gap limit to eps / tan(1.33 deg) =
    10.7 m (``benchmarks/munjer2025.py --lidar vlp16_hires``). The same noise-free 0.3 m trunk,
    one frame: at 6 m the VLP-16's 2-ring cluster (30 points, e = 7.6) is below the window and
    the Hi-Res's 4-ring one (60 points, e = 16.9) is a stem; at 8 m the VLP-16 gives no DBSCAN
    cluster and the Hi-Res a 3-ring one (33 points; e = 21.1, just above the window)."""
    from munjer2025 import resolvable_range  # benchmarks/ (tests/conftest.py's sys.path)
    from stemmap.cloud.munjer import munjer_clusters
    from stemmap.sim.lidar import Stand3D, lidar_preset, simulate_mobile

    assert resolvable_range(lidar_preset("vlp16")) == pytest.approx(7.159, abs=1e-3)
    assert resolvable_range(lidar_preset("vlp16_hires")) == pytest.approx(10.741, abs=1e-3)
    got = {}
    for name in ("vlp16", "vlp16_hires"):
        lidar = lidar_preset(name, range_noise=0.0)
        for r in (6.0, 8.0):
            st = Stand3D(np.array([[r, 0.0]]), np.array([0.3]), np.array([8.0]),
                         np.zeros((1, 2)), np.zeros(1), ground=(0.0, 0.0, 0.0))  # fmt: skip
            mob = simulate_mobile(
                st, np.array([[0.0, 0.0], [0.0, 0.01]]), lidar, height=0.8, yaws=[0, 0], rng=0
            )
            c = munjer_clusters(mob.frames[0].xyz)
            got[name, r] = (int(c.dense.sum()), len(c.stems()))
    assert got == {("vlp16", 6.0): (1, 0), ("vlp16", 8.0): (0, 0),
                   ("vlp16_hires", 6.0): (1, 1), ("vlp16_hires", 8.0): (1, 0)}  # fmt: skip


def test_eb_lidar_map_accuracy(drive: MunjerDrive) -> None:
    m, mm = _map(drive, eb_lidar_observations(drive.frames, drive.times))
    # measured: TA 8, FA 0, FR 5, TR 3. Recall is bounded by the 0.5 m band: beyond ~6 m a
    # trunk has < 20 points (minPts) in its 1-2 rings, and thick trunks fall below e = 10.
    assert m.precision >= 0.85 and m.recall >= 0.5
    assert m.tr == 3 and m.accuracy >= 0.6
    # the map targets
    assert mm.position_rmse <= 0.3
    assert mm.pairwise.mean_percent_error <= 5.0


def test_accumulate_frames_moves_points_into_the_current_frame() -> None:
    """A fixed world point seen from two poses lands on one spot of the later lidar frame;
    the box is applied in each frame's own lidar frame (Munjer §3.2), before the move."""
    world = np.array([[6.0, 2.0, -0.2], [30.0, 0.0, -0.2]])  # the second: outside every box
    poses = np.array([[0.0, 0.0, 0.3], [1.0, 0.5, 0.6]])
    frames = []
    for x, y, th in poses:
        c, s = math.cos(th), math.sin(th)
        d = world[:, :2] - (x, y)
        frames.append(np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1],
                                       world[:, 2])))  # fmt: skip
    out = accumulate_frames(frames, poses, MunjerConfig(window=2))
    assert [len(o) for o in out] == [1, 2]
    np.testing.assert_allclose(out[1][0], out[1][1], atol=1e-12)
    np.testing.assert_allclose(out[1][1], frames[1][0], atol=1e-12)
    with pytest.raises(InputError):
        accumulate_frames(frames, poses[:1], MunjerConfig(window=2))
    with pytest.raises(ConfigError):
        eb_lidar_observations(frames, [0.0, 0.1], MunjerConfig(window=2))
    with pytest.raises(ConfigError):
        MunjerConfig(window=0)


def test_eb_lidar_accumulated_map_accuracy(drive: MunjerDrive) -> None:
    """EB-LiDAR on 5 frames joined with the motion source's poses (dead reckoning of the noisy
    odometry, never the truth): more trees than per frame on this lap, no false accept."""
    poses = rollout(drive.motion_model(), drive.controls(), drive.times, drive.poses[0])
    obs = eb_lidar_observations(drive.frames, drive.times, MunjerConfig(window=5), poses=poses)
    m, mm = _map(drive, obs)
    per_frame, _ = _map(drive, eb_lidar_observations(drive.frames, drive.times))
    # measured: TA 10, FA 0, FR 3, TR 3 (per frame TA 8, FR 5); the 3 misses never come within
    # the 7.2 m a VLP-16 resolves a trunk at (test_trees_beyond_the_resolvable_range)
    assert m.ta >= per_frame.ta and m.recall >= 0.7 and m.precision >= 0.9
    assert mm.position_rmse <= 0.3 and mm.pairwise.mean_percent_error <= 5.0


def test_trees_beyond_the_resolvable_range(drive: MunjerDrive) -> None:
    """Scoring over the trees a 16-beam lidar resolves (eps / tan 2 deg = 7.16 m): a map tree
    on an ineligible tree is neither TA nor FA."""
    r = 0.25 / math.tan(math.radians(2.0))
    ok = drive.trees_in_box(max_range=r)
    assert 0 < ok.sum() < drive.stand2d.n_trees  # measured 10 of 13 on this lap
    assert (ok <= drive.trees_in_box()).all()
    from stemmap.types import StemMap, Tree

    st = drive.stand2d  # the truth as a map
    truth_map = StemMap(
        tuple(Tree(i, float(x), float(y), float(d))
              for i, ((x, y), d) in enumerate(zip(st.trees_xy, st.diameters, strict=True)))
    )  # fmt: skip
    m_all, _ = drive.score(truth_map)
    m_ok, _ = drive.score(truth_map, eligible=ok)
    assert (m_all.ta, m_all.fa, m_all.fr) == (len(ok), 0, 0)
    assert (m_ok.ta, m_ok.fa, m_ok.fr) == (int(ok.sum()), 0, 0)


def test_daim_map_accuracy_with_detector_boxes(drive: MunjerDrive) -> None:
    """DAIM as the pipeline runs it (``MUNJER2025``: noise-scaled clustering radius, width
    check; ``MunjerMapConfig()``: each detection weighed by its depth-model covariance)."""
    obs = daim_observations(
        drive.images,
        drive.depths,
        drive.camera_frames,
        drive.times,
        drive.rig,
        SegmentationDetector(),
    )
    assert obs.source == "vision:munjer2025" and len(obs) > 30
    assert np.isfinite(obs.covs).all()
    m, mm = _map(drive, obs)
    # measured here: TA 11, FA 0, FR 2 (fixed 0.1 m radius: TA 10, FR 3). TA was 12 while
    # DAIM cut pixels, not trunks, at max_depth: tree 8 is nearer than 12 m in one frame
    # only (centre z 11.6 m; then 12.4, 13.2 ...), and was mapped from its far views' noise
    # tails, 0.4-1.2 m short (docs/algorithms/cloud.md, "DAIM: the worst draws")
    assert m.precision >= 0.9 and m.recall >= 0.8
    # D435 depth noise grows as z^2 (9 cm at 5 m): the three-point arc is the weak link;
    # measured 0.187 m (FastSLAM seed 1; 0.194 m before the depth cut and the mean path)
    assert mm.position_rmse <= 0.3
    assert mm.pairwise.mean_percent_error <= 5.0
    # the width check leaves the noise-flattened three-point circles without a diameter: the
    # map's DAIM diameter RMSE: this drive 0.43 m without it, 0.052 m with (benchmark drives
    # 0.34 -> 0.07 m with the fixed radius)
    assert mm.diameter_rmse < 0.1


def test_daim_depth_model_noise_keeps_far_trees_from_pulling_the_map(drive: MunjerDrive) -> None:
    """The noise-scaled radius adds trees seen only from afar, whose three-point centres are
    noisy; weighing each detection by its depth-model covariance (ours) keeps the map within
    0.3 m over FastSLAM seeds 0-2. Before DAIM's depth cut limited the trunk instead of its
    pixels (the far centres were metres short), the constant R drifted above it (0.187 / 0.311
    / 0.346 m against 0.218 / 0.194 / 0.266 m); with unbiased far centres and the posterior-mean
    path both are within it (measured 0.167 / 0.187 / 0.162 m against 0.173 / 0.190 / 0.171
    m), the weighing no worse; same trees mapped."""
    obs = daim_observations(
        drive.images, drive.depths, drive.camera_frames, drive.times, drive.rig,
        SegmentationDetector(),
    )  # fmt: skip
    p0 = (float(drive.poses[0, 0]), float(drive.poses[0, 1]), float(drive.poses[0, 2]))
    rmse: dict[bool, list[float]] = {False: [], True: []}
    for weigh in (False, True):
        for seed in range(3):
            problem = munjer_problem(
                obs, drive.times, drive.controls(), drive.motion_model(), initial_pose=p0
            )
            cfg = MunjerMapConfig(seed=seed, detection_noise=weigh)
            m, mm = drive.score(map_munjer(problem, cfg).stem_map)
            assert m.f1 >= 0.9
            rmse[weigh].append(mm.position_rmse)
    assert max(rmse[True]) <= 0.3
    assert np.mean(rmse[True]) <= np.mean(rmse[False]) + 0.01


def test_daim_map_does_not_depend_on_which_particle_weighs_most(drive: MunjerDrive) -> None:
    """On DAIM's detections FastSLAM's weights stay flat (no resampling in the lap), so the best
    particle's path is one draw of the motion noise: over FastSLAM seeds 0-4 its maps' RMSE
    spread over 0.093-0.252 m (measured). The refinement now maps the detections with the
    posterior-mean path (``MunjerMapConfig.path``, default "mean"): 0.156-0.187 m."""
    obs = daim_observations(
        drive.images, drive.depths, drive.camera_frames, drive.times, drive.rig,
        SegmentationDetector(),
    )  # fmt: skip
    p0 = (float(drive.poses[0, 0]), float(drive.poses[0, 1]), float(drive.poses[0, 2]))
    problem = munjer_problem(obs, drive.times, drive.controls(), drive.motion_model(),
                             initial_pose=p0)  # fmt: skip
    assert MunjerMapConfig().path == "mean"
    rmse = []
    for seed in range(5):
        res = map_munjer(problem, MunjerMapConfig(seed=seed))
        assert res.stats["resamples"] == 0
        rmse.append(drive.score(res.stem_map)[1].position_rmse)
    assert max(rmse) <= 0.2
    assert max(rmse) - min(rmse) < 0.05


def test_ours_beats_both(drive: MunjerDrive) -> None:
    sub = slice(0, None, 2)  # every 2nd frame (5 Hz): test time
    obs = ours_lidar_observations(drive.frames[sub], drive.times[sub])
    m, mm = _map(drive, obs, drive.times[sub])
    eb, _ = _map(drive, eb_lidar_observations(drive.frames, drive.times))
    assert m.f1 >= 0.9 and m.f1 > eb.f1
    assert mm.position_rmse <= 0.3
    assert mm.diameter_rmse < 0.03  # EB-LiDAR's Kasa arcs: ~0.07 m


def test_drive_odometry_is_the_modelled_generator(drive: MunjerDrive) -> None:
    """The drive's motion source is the generator ``sim.odometry_model`` derives (the same
    ``_noisy_odometry``): over 1.5 s windows of this lap (EB-LiDAR's dead-reckoning horizon,
    ~6 m at 4 m/s) the integrated speed error's mean square is the derived ``mean² + var``
    (mostly the 1 % scale, 0.06 m against 0.009 m of white noise: 25 % holds on one lap) and
    the heading error's is within chi-square bounds for the 10 windows (white-noise dominated).
    ``MunjerDrive.motion_model`` does not use this derivation: docs/algorithms/slam-frontends.md,
    "Motion noise"."""
    noise = OdometryNoise(**drive.params["odometry_noise"])  # type: ignore[arg-type]
    rate = float(drive.params["odom_rate_hz"])  # type: ignore[arg-type]
    n = round(1.5 * rate)
    k = drive.odometry.speed.size // n
    assert k >= 8
    speed = float(np.median(drive.odometry_true.speed))
    m = increment_error_moments(noise, duration=n / rate, rate_hz=rate, speed=speed)
    dv = drive.odometry.speed - drive.odometry_true.speed
    dw = drive.odometry.yaw_rate - drive.odometry_true.yaw_rate
    dist = dv[: k * n].reshape(k, n).sum(1) / rate
    head = dw[: k * n].reshape(k, n).sum(1) / rate
    assert np.mean(dist**2) == pytest.approx(m.distance_mse, rel=0.25)
    assert 0.3 < np.mean(head**2) / m.heading_mse < 2.2


def test_controls_from_trajectory_round_trip(drive: MunjerDrive) -> None:
    """A pose-output motion source (e.g. lidar + IMU odometry) plugs in: its controls dead-
    reckon back to the same poses."""
    traj = Trajectory(drive.times, drive.poses, frame="odom")
    ctrl, model = controls_from_trajectory(traj, sigma_speed=0.05, sigma_yaw_rate=0.002)
    obs = eb_lidar_observations(drive.frames[:5], drive.times[:5])
    p0 = tuple(float(v) for v in drive.poses[0])
    problem = munjer_problem(obs, drive.times, ctrl, model, initial_pose=p0)  # type: ignore[arg-type]
    dr = dead_reckoning(problem)
    err = np.hypot(*(dr.poses[:, :2] - drive.poses[:, :2]).T)
    # chords of 0.4 m on 4 m radius turns: the arc vs chord difference stays below 1 cm
    assert err.max() < 0.05
    assert model.sigma_speed == 0.05


def test_score_frames_per_frame_view(drive: MunjerDrive) -> None:
    """The per-frame scoring beside the paper's map scoring (MunjerDrive.score_frames): the
    truth itself, put in every frame's lidar frame, scores TA = every counted (frame, tree)
    pair and no FA / FR; the same positions 1.5 m off (beyond the 1.0 m gate) are all FA.
    EB-LiDAR's frame detections are precise but find a tree in only a fraction of the frames
    it is visible in, while its map (3 detections confirm a tree) finds most of them: the
    paper's F1 is a map score (§4, Table 2), so it is the comparable one."""
    st = drive.stand2d
    counted = np.zeros((len(drive.frames), st.n_trees), dtype=bool)
    for f, fr in enumerate(drive.frames):
        lab = fr.fields["label"][pass_through(fr.xyz, x=(0, 10), y=(-10, 10), z=(-0.5, 0))]
        n = np.bincount(lab[(lab >= 0) & (lab < st.n_trees)].astype(int), minlength=st.n_trees)
        counted[f] = n >= 20
    f_idx, t_idx = np.nonzero(counted)
    x, y, th = drive.poses[f_idx].T
    d = st.trees_xy[t_idx] - np.column_stack((x, y))
    local = np.column_stack((np.cos(th) * d[:, 0] + np.sin(th) * d[:, 1],
                             -np.sin(th) * d[:, 0] + np.cos(th) * d[:, 1]))  # fmt: skip
    k = len(f_idx)

    def obs(centers: np.ndarray) -> StemObservations:
        return StemObservations(
            centers=centers, radii=st.radii[t_idx], covs=np.full((k, 3, 3), np.nan),
            n_points=np.full(k, 50), arc_deg=np.full(k, np.nan), widths=np.full(k, np.nan),
            quality=np.ones(k), index=f_idx, times=drive.times[f_idx], source="truth",
            frame="lidar",
        )  # fmt: skip

    perfect = drive.score_frames(obs(local))
    assert (perfect.ta, perfect.fa, perfect.fr) == (k, 0, 0) and perfect.n_frames == len(counted)
    off = drive.score_frames(obs(local + np.array([0.0, 1.5])))
    assert (off.ta, off.fa, off.fr) == (0, k, k)
    eb = eb_lidar_observations(drive.frames, drive.times)
    pf = drive.score_frames(eb)
    m, _ = _map(drive, eb)
    # measured on this lap: per frame TA 67, FA 0, FR 153 (precision 1.0, recall 0.30, F1 0.47);
    # map TA 8, FA 0, FR 5 (recall 0.62, F1 0.76)
    assert pf.precision >= 0.9 and 0.15 <= pf.recall <= 0.45
    assert m.recall >= pf.recall + 0.2
