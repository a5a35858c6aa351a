"""What makes a simulated stand realistic: non-tree clutter, understory and non-circular trunks.

Each function takes a :class:`~stemmap.sim.forest.Stand` and returns a new one (the input is
frozen and never changed). :func:`add_clutter` adds obstacles that are not trees (bushes, thin
branches, walls, fences, rocks); :func:`add_understory` adds what grows against real trunks
(thin stems beside them, low branches leaving them); :func:`make_trunks_noncircular` replaces
round trunks by polygons owned by the tree (:func:`stemmap.sim.outline.trunk_outline`).
Non-tree objects are recorded one per object in ``stand.clutter_objects_xy`` /
``stand.clutter_kinds`` (see :data:`CLUTTER_KINDS`) so true rejects can be counted.

Also importable from :mod:`stemmap.sim.forest`, where the stand layouts live.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError
from stemmap.sim.outline import rough_radius, trunk_outline
from stemmap.types import FloatArray

if TYPE_CHECKING:  # forest.py re-exports this module's names, so no runtime import of it
    from stemmap.sim.forest import RngLike, Stand

__all__ = [
    "CLUTTER_KINDS",
    "add_clutter",
    "add_understory",
    "make_trunks_noncircular",
]

#: Kinds of non-tree objects the simulator places.
CLUTTER_KINDS = ("bush", "branch", "wall", "fence", "rock", "understory")


def _polygon_segments(xy: FloatArray) -> FloatArray:
    """Closed polygon (V, 2) -> (V, 4) segments."""
    return np.column_stack((xy, np.roll(xy, -1, axis=0)))


def _with_clutter(
    stand: Stand,
    circ_xy: list[FloatArray],
    circ_r: list[FloatArray],
    segs: list[FloatArray],
    owners: list[NDArray[np.int64]],
    obj_xy: list[FloatArray],
    kinds: list[str],
    extents: list[float],
) -> Stand:
    """``stand`` with the accumulated clutter lists (each starting with the stand's own)."""
    return replace(
        stand,
        clutter_xy=np.vstack(circ_xy),
        clutter_radius=np.concatenate(circ_r),
        segments=np.vstack(segs),
        segment_owner=np.concatenate(owners),
        clutter_objects_xy=np.vstack(obj_xy),
        clutter_kinds=tuple(kinds),
        clutter_objects_extent=np.asarray(extents, dtype=np.float64),
    )


def add_clutter(
    stand: Stand,
    *,
    n_bushes: int = 0,
    n_branches: int = 0,
    n_walls: int = 0,
    n_fences: int = 0,
    n_rocks: int = 0,
    clearance: float = 0.3,
    rng: RngLike = None,
) -> Stand:
    """Add non-tree objects that reflect laser beams.

    Parameters
    ----------
    stand : Stand
    n_bushes : int
        Bushes: 6-15 thin stems (circles of radius 0.5-2.5 cm) scattered within 0.2-0.6 m of a
        centre -- many small, jumpy returns.
    n_branches : int
        Thin branches at scan height: straight segments 0.4-2.0 m long, random orientation.
    n_walls : int
        Walls: straight segments 4-12 m long.
    n_fences : int
        Fences: a rail (segment 5-15 m) with posts (circles of radius 5 cm) every 2 m.
    n_rocks : int
        Rocks: irregular polygons of mean radius 0.25-0.7 m (strongly non-circular outline).
    clearance : float, metres
        Minimum gap between a new object's centre region and any trunk surface.
    rng : numpy Generator or int seed

    Returns
    -------
    Stand
        A new stand with the clutter appended (``segment_owner = -1``) and one entry per object
        in ``clutter_objects_xy`` / ``clutter_kinds``.
    """
    for name, v in (
        ("n_bushes", n_bushes),
        ("n_branches", n_branches),
        ("n_walls", n_walls),
        ("n_fences", n_fences),
        ("n_rocks", n_rocks),
    ):
        if v < 0:
            raise ConfigError(f"{name} must be >= 0, got {v}.")
    gen = np.random.default_rng(rng)
    x0, y0, x1, y1 = stand.bounds
    if not (x1 > x0 and y1 > y0):
        if stand.n_trees:
            x0, y0 = stand.trees_xy.min(axis=0) - 2
            x1, y1 = stand.trees_xy.max(axis=0) + 2
        else:
            x0, y0, x1, y1 = 0.0, 0.0, 20.0, 20.0

    def free_point(extent: float) -> FloatArray:
        for _ in range(500):
            p = gen.uniform((x0, y0), (x1, y1))
            if stand.n_trees == 0:
                return p
            gap = np.hypot(*(stand.trees_xy - p).T) - stand.radii
            if gap.min() > extent + clearance:
                return p
        raise ConfigError(
            "add_clutter could not find free space for an object; the stand is too dense."
        )

    def free_segment(lo: float, hi: float) -> tuple[FloatArray, FloatArray]:
        """Centre and half-vector of a segment whose every point clears the trunks."""
        for _ in range(500):
            length = gen.uniform(lo, hi)
            c = gen.uniform((x0, y0), (x1, y1))
            a = gen.uniform(0, np.pi)
            d = 0.5 * length * np.array([math.cos(a), math.sin(a)])
            if stand.n_trees == 0:
                return c, d
            rel = stand.trees_xy - c
            t = np.clip(rel @ d / (d @ d), -1.0, 1.0)
            dist = np.hypot(*(rel - t[:, None] * d).T) - stand.radii
            if dist.min() > clearance:
                return c, d
        raise ConfigError(
            f"add_clutter could not fit a {lo}-{hi} m long object between the trunks; the "
            "stand is too dense for walls/fences/branches."
        )

    circ_xy: list[FloatArray] = [stand.clutter_xy]
    circ_r: list[FloatArray] = [stand.clutter_radius]
    segs: list[FloatArray] = [stand.segments]
    owners: list[NDArray[np.int64]] = [stand.segment_owner]
    obj_xy: list[FloatArray] = [stand.clutter_objects_xy]
    kinds: list[str] = list(stand.clutter_kinds)
    extents: list[float] = list(stand.clutter_objects_extent)

    def add_segments(s: FloatArray) -> None:
        segs.append(s.reshape(-1, 4))
        owners.append(np.full(s.reshape(-1, 4).shape[0], -1, dtype=np.int64))

    for _ in range(n_bushes):
        spread = gen.uniform(0.2, 0.6)
        c = free_point(spread)
        m = int(gen.integers(6, 16))
        ang = gen.uniform(0, 2 * np.pi, m)
        rad = spread * np.sqrt(gen.random(m))
        circ_xy.append(c + np.column_stack((rad * np.cos(ang), rad * np.sin(ang))))
        circ_r.append(gen.uniform(0.005, 0.025, m))
        obj_xy.append(c[None])
        kinds.append("bush")
        extents.append(spread)
    for _ in range(n_branches):
        c, d = free_segment(0.4, 2.0)
        length = 2 * float(np.hypot(*d))
        add_segments(np.concatenate((c - d, c + d)))
        obj_xy.append(c[None])
        kinds.append("branch")
        extents.append(length / 2)
    for _ in range(n_walls):
        c, d = free_segment(4.0, 12.0)
        length = 2 * float(np.hypot(*d))
        add_segments(np.concatenate((c - d, c + d)))
        obj_xy.append(c[None])
        kinds.append("wall")
        extents.append(length / 2)
    for _ in range(n_fences):
        c, d = free_segment(5.0, 15.0)
        length = 2 * float(np.hypot(*d))
        u = d / np.hypot(*d)
        add_segments(np.concatenate((c - 0.5 * length * u, c + 0.5 * length * u)))
        posts = c + np.outer(np.arange(-length / 2, length / 2 + 1e-9, 2.0), u)
        # posts stand just beside the rail so both reflect
        n_vec = np.array([-u[1], u[0]])
        circ_xy.append(posts + 0.06 * n_vec)
        circ_r.append(np.full(posts.shape[0], 0.05))
        obj_xy.append(c[None])
        kinds.append("fence")
        extents.append(length / 2)
    for _ in range(n_rocks):
        radius = gen.uniform(0.25, 0.7)
        c = free_point(radius * 1.5)
        nv = 24
        rr = rough_radius(nv, radius, 0.3, gen)
        phi = 2 * np.pi * np.arange(nv) / nv
        poly = c + np.column_stack((rr * np.cos(phi), rr * np.sin(phi)))
        add_segments(_polygon_segments(poly))
        obj_xy.append(c[None])
        kinds.append("rock")
        extents.append(float(rr.max()))

    return _with_clutter(stand, circ_xy, circ_r, segs, owners, obj_xy, kinds, extents)


def add_understory(
    stand: Stand,
    *,
    stems_per_tree: float = 1.0,
    branches_per_tree: float = 0.5,
    rng: RngLike = None,
) -> Stand:
    """Add what grows against real trunks at scan height (issue 11): thin understory stems
    beside the trunks and low branches leaving them.

    Parameters
    ----------
    stand : Stand
    stems_per_tree : float, >= 0
        Mean number (Poisson) of thin stems per tree: circles of radius 0.5-2.5 cm whose surface
        is 2-50 cm from the trunk's surface (a sapling, a sucker, a shrub stem: the
        segmentation may merge them with the trunk).
    branches_per_tree : float, >= 0
        Mean number (Poisson) of low branches per tree: straight segments 0.2-1.0 m long
        starting on the trunk surface (its circle of DBH) at a random azimuth, pointing outward
        within +-60 degrees of the radial direction (the lidR dbh slice's trunk has one: the
        trunk and the branch are one segment from most directions).
    rng : numpy Generator or int seed

    Returns
    -------
    Stand
        A new stand with the additions as clutter (kinds ``"understory"`` and ``"branch"``).
    """
    if not (stems_per_tree >= 0 and branches_per_tree >= 0):
        raise ConfigError(
            "add_understory needs stems_per_tree >= 0 and branches_per_tree >= 0, got "
            f"{stems_per_tree}, {branches_per_tree}."
        )
    gen = np.random.default_rng(rng)
    circ_xy: list[FloatArray] = [stand.clutter_xy]
    circ_r: list[FloatArray] = [stand.clutter_radius]
    segs: list[FloatArray] = [stand.segments]
    owners: list[NDArray[np.int64]] = [stand.segment_owner]
    obj_xy: list[FloatArray] = [stand.clutter_objects_xy]
    kinds = list(stand.clutter_kinds)
    extents = list(stand.clutter_objects_extent)
    for c, r in zip(stand.trees_xy, stand.radii, strict=True):
        for _ in range(int(gen.poisson(stems_per_tree))):
            rs = float(gen.uniform(0.005, 0.025))
            az = float(gen.uniform(0, 2 * np.pi))
            d = r + float(gen.uniform(0.02, 0.5)) + rs
            p = c + d * np.array([math.cos(az), math.sin(az)])
            circ_xy.append(p[None])
            circ_r.append(np.array([rs]))
            obj_xy.append(p[None])
            kinds.append("understory")
            extents.append(rs)
        for _ in range(int(gen.poisson(branches_per_tree))):
            az = float(gen.uniform(0, 2 * np.pi))
            length = float(gen.uniform(0.2, 1.0))
            out = az + float(gen.uniform(-math.pi / 3, math.pi / 3))
            p0 = c + r * np.array([math.cos(az), math.sin(az)])
            p1 = p0 + length * np.array([math.cos(out), math.sin(out)])
            segs.append(np.concatenate((p0, p1))[None])
            owners.append(np.full(1, -1, dtype=np.int64))
            obj_xy.append((0.5 * (p0 + p1))[None])
            kinds.append("branch")
            extents.append(length / 2)
    return _with_clutter(stand, circ_xy, circ_r, segs, owners, obj_xy, kinds, extents)


def make_trunks_noncircular(
    stand: Stand,
    *,
    ellipticity: float = 0.1,
    roughness: float = 0.02,
    n_vertices: int = 48,
    fraction: float = 1.0,
    bark_rms: float = 0.0,
    lean_deg: float = 0.0,
    buttress: float = 0.0,
    n_lobes: int = 4,
    rng: RngLike = None,
) -> Stand:
    """Replace round trunks by polygons (:func:`stemmap.sim.outline.trunk_outline`), owned by
    the tree: an ellipse with rough bark, optionally bark ridges, lean and buttress lobes.

    Parameters
    ----------
    stand : Stand
    ellipticity : float in [0, 0.5)
        Semi-axes are ``r (1 + e)`` and ``r (1 - e)`` with a random orientation, so the mean of
        the two caliper diameters stays the tree's DBH (``stand.diameters`` is unchanged).
    roughness : float, >= 0
        Relative RMS of a smooth random radius perturbation (out-of-roundness), e.g. 0.02 = 2 %.
    n_vertices : int, >= 8
        Polygon vertices per trunk (48 keeps the polygon chord error below 0.3 % of r; bark
        ridges need more, e.g. 240).
    fraction : float in [0, 1]
        Share of trees made non-circular (chosen at random).
    bark_rms : float, metres
        RMS of cm-scale bark ridges (harmonics 9 to n_vertices/4, 1/k spectrum).
    lean_deg : float, degrees
        Largest stem lean; each chosen tree leans uniformly in [0, lean_deg] (random azimuth),
        which stretches its horizontal section by 1/cos(lean). ``stand.diameters`` stays the
        diameter across the stem axis.
    buttress : float
        Relative height of buttress lobes (``n_lobes`` of them) at scan height.
    rng : numpy Generator or int seed
    """
    if not (0 <= ellipticity < 0.5 and roughness >= 0 and n_vertices >= 8 and 0 <= fraction <= 1):
        raise ConfigError(
            "make_trunks_noncircular needs 0 <= ellipticity < 0.5, roughness >= 0, "
            f"n_vertices >= 8, 0 <= fraction <= 1; got {ellipticity}, {roughness}, "
            f"{n_vertices}, {fraction}."
        )
    gen = np.random.default_rng(rng)
    chosen = (gen.random(stand.n_trees) < fraction) & ~stand.tree_is_polygon
    segs = [stand.segments]
    owners = [stand.segment_owner]
    for i in np.flatnonzero(chosen):
        lean = float(gen.uniform(0.0, lean_deg)) if lean_deg > 0 else 0.0
        outline = trunk_outline(
            float(stand.radii[i]),
            gen,
            n_vertices=n_vertices,
            ellipticity=ellipticity,
            roughness=roughness,
            bark_rms=bark_rms,
            lean_deg=lean,
            buttress=buttress,
            n_lobes=n_lobes,
        )
        segs.append(_polygon_segments(stand.trees_xy[i] + outline))
        owners.append(np.full(n_vertices, i, dtype=np.int64))
    return replace(
        stand,
        segments=np.vstack(segs),
        segment_owner=np.concatenate(owners),
        tree_is_polygon=stand.tree_is_polygon | chosen,
    )
