"""Simulated laser + camera test scenes for fusion, and their scoring against ground truth.

:func:`fusion_scene` builds a stand in front of the rig with three kinds of distractors, each
fooling one sensor:

* bushes (green, 0.2-0.6 m wide): trunk-like laser width -> a laser-only false positive;
  a colour rule strips them;
* posts / stumps (bark-coloured, 0.7-1.2 m wide): bark-like in the image -> a vision-only false
  positive; too wide for the laser's width band;
* short walls (grey segments): rejected by both.

:func:`score_detections` scores detections by their ground-truth identity (what the laser beams
or the region's pixels actually hit), so laser-only, vision-only and fused decisions are scored
the same way, over the trees both sensors can see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.fusion.associate import LaserRois
from stemmap.fusion.fuse import FusionParams
from stemmap.sim.camera import CameraRig, Scene, render_scene, xue2018_rig
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import ScannerModel
from stemmap.types import Pose2

__all__ = [
    "Counts",
    "evaluate_fusion",
    "fusion_scene",
    "region_identity",
    "roi_identity",
    "score_detections",
]


def fusion_scene(
    rng: np.random.Generator | int | None = None,
    *,
    rig: CameraRig | None = None,
    n_trees: int = 8,
    n_bushes: int = 4,
    n_posts: int = 2,
    n_walls: int = 1,
    depth: tuple[float, float] = (2.5, 12.0),
    scanner: ScannerModel | None = None,
) -> Scene:
    """One random scene in the camera's view (laser at the origin, facing +x)."""
    gen = np.random.default_rng(rng)
    rig = rig or xue2018_rig()
    half = math.radians(28.0)
    objs: list[tuple[float, float, float]] = []

    def place(r_min: float, r_max: float) -> tuple[float, float, float]:
        for _ in range(500):
            d = gen.uniform(*depth)
            a = gen.uniform(-half, half)
            rad = gen.uniform(r_min, r_max)
            x, y = d * math.cos(a), d * math.sin(a)
            if all(math.hypot(x - ox, y - oy) > rad + orad + 0.6 for ox, oy, orad in objs):
                objs.append((x, y, rad))
                return x, y, rad
        return math.nan, math.nan, math.nan

    trees = [place(0.08, 0.22) for _ in range(n_trees)]
    bushes = [place(0.1, 0.3) for _ in range(n_bushes)]
    posts = [place(0.35, 0.6) for _ in range(n_posts)]
    walls = []
    for _ in range(n_walls):
        x, y, _r = place(0.6, 1.2)
        if math.isfinite(x):
            a = gen.uniform(0, math.pi)
            L = gen.uniform(1.0, 2.5)
            walls.append(
                [
                    x - L / 2 * math.cos(a),
                    y - L / 2 * math.sin(a),
                    x + L / 2 * math.cos(a),
                    y + L / 2 * math.sin(a),
                ]
            )
    t = np.array([o for o in trees if math.isfinite(o[0])]).reshape(-1, 3)
    c = np.array([o for o in bushes + posts if math.isfinite(o[0])]).reshape(-1, 3)
    n_b = sum(math.isfinite(o[0]) for o in bushes)
    mimic = np.arange(c.shape[0]) >= n_b
    stand = Stand(
        t[:, :2],
        2 * t[:, 2],
        clutter_xy=c[:, :2],
        clutter_radius=c[:, 2],
        segments=np.asarray(walls).reshape(-1, 4),
    )
    sc = scanner or ScannerModel(angle_increment=math.radians(0.5), range_noise=0.01, range_max=20)
    return render_scene(stand, Pose2(0.0, 0.0, 0.0), rig, scanner=sc, mimic_mask=mimic, rng=gen)


def roi_identity(rois: LaserRois, hit_id: NDArray[np.int64]) -> NDArray[np.int64]:
    """Ground truth of each laser RoI: the majority hit id of its beams (tree index, or < 0)."""
    out = np.full(len(rois), -1, dtype=np.int64)
    lab = rois.labels
    h = np.asarray(hit_id)[rois.beam]
    for k in range(len(rois)):
        vals, cnt = np.unique(h[lab == k], return_counts=True)
        out[k] = vals[np.argmax(cnt)]
    return out


def region_identity(
    label_image: NDArray[np.int32],
    boxes: ArrayLike,
    masks: NDArray[np.int32] | None = None,
    region_labels: ArrayLike | None = None,
) -> NDArray[np.int64]:
    """Ground truth of each image region: the majority truth label of its pixels (the region's
    own pixels when ``masks``/``region_labels`` are given, else its box)."""
    b = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    out = np.full(b.shape[0], -1, dtype=np.int64)
    for k, (x, y, w, h) in enumerate(b):
        lab = label_image[y : y + h, x : x + w]
        if masks is not None and region_labels is not None:
            sel = masks[y : y + h, x : x + w] == np.asarray(region_labels)[k]
            lab = lab[sel]
        vals, cnt = np.unique(lab, return_counts=True)
        if vals.size:
            out[k] = vals[np.argmax(cnt)]
    return out


@dataclass(frozen=True)
class Counts:
    """True positives, false positives, false negatives; precision, recall, F1."""

    tp: int
    fp: int
    fn: int

    @property
    def precision(self) -> float:
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else math.nan

    @property
    def recall(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else math.nan

    @property
    def f1(self) -> float:
        d = 2 * self.tp + self.fp + self.fn
        return 2 * self.tp / d if d else math.nan

    def __add__(self, other: Counts) -> Counts:
        return Counts(self.tp + other.tp, self.fp + other.fp, self.fn + other.fn)


def score_detections(
    identities: ArrayLike, accepted: ArrayLike, eligible: NDArray[np.bool_]
) -> Counts:
    """Score accepted detections by identity: a tree counts once (duplicates are false
    positives), non-trees are false positives, eligible trees never accepted are misses.
    Accepted detections of ineligible trees are ignored."""
    ids = np.asarray(identities, dtype=np.int64)[np.asarray(accepted, dtype=bool)]
    trees = ids[ids >= 0]
    trees_e = trees[eligible[trees]]
    uniq = np.unique(trees_e)
    tp = int(uniq.size)
    fp = int((ids < 0).sum() + (trees_e.size - uniq.size))
    fn = int(eligible.sum() - tp)
    return Counts(tp, fp, fn)


def evaluate_fusion(
    seeds: ArrayLike,
    *,
    rig: CameraRig | None = None,
    bpa: str = "forest",
    fusion_params: FusionParams | None = None,
    **scene_options: object,
) -> dict[str, Counts]:
    """Laser-only, vision-only, Xue-fused and our fused detections on simulated scenes.

    For every seed: :func:`fusion_scene` -> laser RoIs
    (:func:`~stemmap.fusion.associate.laser_rois`) and stripping segmentation (preset
    "xue2018") -> :func:`~stemmap.fusion.fuse.fuse_xue2018` (BPA preset ``bpa``) and
    :func:`~stemmap.fusion.fuse.fuse_ours`. Laser-only decisions are
    eq. 17 on the laser BPA of the RoIs that project into the image; vision-only decisions are
    eq. 17 on the vision BPA of every region. Eligible trees: hit by >= 3 beams and visible in
    the image. Counts are summed over the seeds.
    """
    from stemmap.fusion.associate import laser_rois
    from stemmap.fusion.fuse import fuse_ours, fuse_xue2018
    from stemmap.vision.camera import laser_plane_homography
    from stemmap.vision.segment import segment_trunks

    rig = rig or xue2018_rig()
    G = laser_plane_homography(rig.camera, rig.laser_to_camera)
    tot = {k: Counts(0, 0, 0) for k in ("laser", "vision", "fused_xue2018", "fused_ours")}
    for s in np.asarray(seeds).reshape(-1):
        sc = fusion_scene(int(s), rig=rig, **scene_options)  # type: ignore[arg-type]
        rois = laser_rois(sc.scan)
        seg = segment_trunks(sc.image)
        reg = seg.regions
        rid = roi_identity(rois, sc.truth.hit_id)
        gid = region_identity(sc.truth.label, reg.boxes, seg.labels, reg.label)
        hit = sc.truth.hit_id
        hits = np.bincount(hit[hit >= 0], minlength=sc.stand.n_trees)
        elig = (hits >= 3) & sc.truth.tree_visible
        fx = fuse_xue2018(rois, reg, G, image_width=rig.camera.width, bpa=bpa)
        fo = fuse_ours(rois, reg, G, sc.image, rig.camera, laser_to_camera=rig.laser_to_camera)
        in_view = np.concatenate((fx.association.pairs[:, 0], fx.association.laser_only))

        tot["laser"] += score_detections(rid[in_view], fx.laser_only_trunk[in_view], elig)
        tot["vision"] += score_detections(gid, fx.vision_only_trunk, elig)
        tot["fused_xue2018"] += score_detections(
            _identity(fx.laser_index, fx.region_index, rid, gid), fx.is_trunk, elig
        )
        tot["fused_ours"] += score_detections(
            _identity(fo.laser_index, fo.region_index, rid, gid), fo.is_trunk, elig
        )
    return tot


def _identity(
    li: NDArray[np.int64], ri: NDArray[np.int64], rid: NDArray[np.int64], gid: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Identity of fused objects: the laser RoI's when there is one, else the region's."""
    g = gid[np.maximum(ri, 0)] if len(gid) else np.full(ri.shape, -1)
    r = rid[np.maximum(li, 0)] if len(rid) else np.full(li.shape, -1)
    return np.where(li >= 0, r, g)
