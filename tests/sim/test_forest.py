import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.sim import (
    CLUTTER_KINDS,
    Stand,
    add_clutter,
    clustered_stand,
    make_trunks_noncircular,
    random_stand,
    row_stand,
    sample_dbh,
    stand_from_spec,
)


def _min_gap(s: Stand) -> float:
    d = np.hypot(*(s.trees_xy[:, None] - s.trees_xy[None]).transpose(2, 0, 1))
    gap = d - (s.radii[:, None] + s.radii[None])
    np.fill_diagonal(gap, np.inf)
    return float(gap.min())


@pytest.mark.parametrize("dist", ["normal", "weibull"])
def test_sample_dbh_moments(dist):
    d = sample_dbh(20_000, distribution=dist, mean=0.3, std=0.08, dbh_min=0.01, dbh_max=2.0, rng=1)
    # truncation at 0.01 m removes < 0.01 % of the mass: moments within sampling error
    # (std of the mean 0.08 / sqrt(20000) = 0.0006 -> 0.003 is 5 sigma; std within 3 %)
    assert d.mean() == pytest.approx(0.3, abs=0.003)
    assert d.std() == pytest.approx(0.08, rel=0.03)


def test_sample_dbh_truncation_and_errors():
    d = sample_dbh(1000, mean=0.3, std=0.2, dbh_min=0.1, dbh_max=0.4, rng=2)
    assert d.min() >= 0.1 and d.max() <= 0.4 and d.size == 1000
    with pytest.raises(ConfigError):
        sample_dbh(10, distribution="lognormal")  # type: ignore[arg-type]
    with pytest.raises(ConfigError):
        sample_dbh(10, dbh_min=0.5, dbh_max=0.4)
    with pytest.raises(ConfigError, match="widen"):
        sample_dbh(10, mean=0.3, std=0.001, dbh_min=1.0, dbh_max=1.1)


def test_clustered_stand_is_more_clumped_than_random():
    c = clustered_stand(80, (50, 50), n_clusters=4, cluster_std=3.0, rng=3)
    r = random_stand(80, (50, 50), min_spacing=0.8, rng=3)
    assert c.n_trees == r.n_trees == 80
    assert _min_gap(c) >= 0.8

    def mean_nn(s: Stand) -> float:
        d = np.hypot(*(s.trees_xy[:, None] - s.trees_xy[None]).transpose(2, 0, 1))
        np.fill_diagonal(d, np.inf)
        return float(d.min(axis=1).mean())

    # clumping shortens nearest-neighbour distances (Clark-Evans ratio < 1)
    assert mean_nn(c) < 0.8 * mean_nn(r)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda **kw: random_stand(**kw, min_spacing=0.8),
         r"could place only \d+ of 300 trees in 12.0 x 10.0 m with spacing 0.8 m; enlarge"),
        (lambda **kw: clustered_stand(**kw, n_clusters=4, cluster_std=3.0),
         r"could place only \d+ of 300 clustered trees \(n_clusters=4, cluster_std=3.0 m"),
    ],
)  # fmt: skip
def test_random_and_clustered_stands_share_dbh_spacing_and_bounds(make, match):
    """Both layouts draw the DBH in the window asked for, keep the surface gap, span the stand
    from the origin, and say how many trees fit when they do not."""
    s = make(n_trees=40, size=(40.0, 30.0), dbh_min=0.2, dbh_max=0.35, rng=12)
    assert s.n_trees == 40 and s.bounds == (0.0, 0.0, 40.0, 30.0)
    assert s.diameters.min() >= 0.2 and s.diameters.max() <= 0.35
    assert _min_gap(s) >= 0.8
    assert np.all((s.trees_xy >= 0.0) & (s.trees_xy <= (40.0, 30.0)))
    with pytest.raises(ConfigError, match=match):
        make(n_trees=300, size=(12.0, 10.0), rng=12)


def test_row_stand_geometry():
    s = row_stand(4, 10, row_spacing=4.0, tree_spacing=3.0, jitter=0.0, heading=0.0, rng=4)
    assert s.n_trees == 40
    np.testing.assert_allclose(np.unique(s.trees_xy[:, 1]), [0.0, 4.0, 8.0, 12.0], atol=1e-12)
    np.testing.assert_allclose(np.unique(s.trees_xy[:, 0]), np.arange(10) * 3.0, atol=1e-12)
    rot = row_stand(2, 5, heading=math.pi / 2, jitter=0.0, rng=4)
    np.testing.assert_allclose(rot.trees_xy[:5, 0], 0.0, atol=1e-12)  # row along +y
    missing = row_stand(20, 20, missing=0.25, rng=5)
    # binomial(400, 0.75): 5 sigma = 43 trees
    assert abs(missing.n_trees - 300) < 43


def test_add_clutter_places_every_kind_clear_of_trunks():
    s = random_stand(40, (40, 40), rng=6)
    c = add_clutter(s, n_bushes=3, n_branches=2, n_walls=1, n_fences=1, n_rocks=2, rng=7)
    assert c.clutter_kinds.count("bush") == 3 and c.clutter_kinds.count("rock") == 2
    assert set(c.clutter_kinds) <= set(CLUTTER_KINDS)
    assert c.clutter_objects_xy.shape == (9, 2) and c.clutter_objects_extent.shape == (9,)
    np.testing.assert_array_equal(c.trees_xy, s.trees_xy)
    # bush stems stay off the trunks: every clutter circle is outside every trunk
    d = np.hypot(*(c.clutter_xy[:, None] - s.trees_xy[None]).transpose(2, 0, 1))
    assert np.all(d - s.radii[None] - c.clutter_radius[:, None] > 0)
    assert np.all(c.segment_owner == -1)


def test_noncircular_fraction_and_subset():
    s = make_trunks_noncircular(random_stand(50, (40, 40), rng=8), fraction=0.5, rng=9)
    k = int(s.tree_is_polygon.sum())
    assert 10 < k < 40  # binomial(50, 0.5): 4 sigma
    assert s.segments.shape[0] == 48 * k
    keep = np.zeros(50, dtype=bool)
    keep[::2] = True
    sub = s.subset_trees(keep)
    assert sub.n_trees == 25
    assert sub.segments.shape[0] == 48 * int(s.tree_is_polygon[keep].sum())
    assert sub.segment_owner.max() < 25


def test_stand_validation():
    with pytest.raises(InputError, match="diameters"):
        Stand([[0, 0], [1, 1]], [0.3])
    with pytest.raises(InputError, match="positive"):
        Stand([[0, 0]], [0.0])
    with pytest.raises(InputError, match="segment_owner"):
        Stand([[0, 0]], [0.3], segments=[[0, 0, 1, 1]], segment_owner=[3])
    with pytest.raises(InputError, match="clutter_kinds"):
        Stand([[0, 0]], [0.3], clutter_objects_xy=[[1, 1]])
    with pytest.raises(InputError, match="finite"):
        Stand([[0, 0]], [0.3], segments=[[0, 0, np.nan, 1]])
    with pytest.raises(InputError, match="radius"):
        Stand([[0, 0]], [0.3], clutter_xy=[[1, 1]], clutter_radius=[0.0])
    with pytest.raises(ConfigError):
        add_clutter(Stand([[0, 0]], [0.3]), n_bushes=-1)
    with pytest.raises(ConfigError):
        make_trunks_noncircular(Stand([[0, 0]], [0.3]), ellipticity=0.7)
    with pytest.raises(ConfigError, match="could place only"):
        random_stand(500, (5, 5))


def test_to_stem_map_carries_the_truth():
    s = random_stand(12, (20, 20), rng=11)
    sm = s.to_stem_map()
    assert len(sm) == 12 and sm.frame == "world"
    np.testing.assert_allclose(sm.xy, s.trees_xy)
    np.testing.assert_allclose(sm.diameters, s.diameters)
    assert [t.id for t in sm] == list(range(12))


def _same_stand(a: Stand, b: Stand) -> bool:
    fields = ("trees_xy", "diameters", "clutter_xy", "clutter_radius", "segments")
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields) and (
        a.clutter_kinds == b.clutter_kinds and a.bounds == b.bounds
    )


def test_stand_from_spec_is_random_stand_then_clutter_from_one_generator():
    """The spec reads as the explicit calls (same draws, same order), the scalar size is a
    square, ``n_trees=`` overrides the spec, and a Generator passed in is advanced as if the
    caller had made the calls (the demo and the benchmarks draw the drive from it next)."""
    spec = {"layout": "random", "n_trees": 40, "size_m": [35.0, 30.0], "dbh_mean_m": 0.25,
            "dbh_std_m": 0.05, "dbh_min_m": 0.1, "min_spacing_m": 1.0}  # fmt: skip
    clutter = {"n_bushes": 2, "n_branches": 1, "n_walls": 1, "n_fences": 0, "n_rocks": 3}
    g1, g2 = np.random.default_rng(5), np.random.default_rng(5)
    got = stand_from_spec(spec, clutter, rng=g1)
    ref = random_stand(40, (35.0, 30.0), dbh_mean=0.25, dbh_std=0.05, dbh_min=0.1,
                       min_spacing=1.0, rng=g2)  # fmt: skip
    ref = add_clutter(ref, **clutter, rng=g2)
    assert _same_stand(got, ref)
    assert got.clutter_kinds.count("rock") == 3
    assert g1.random() == g2.random()  # both streams are at the same place afterwards

    square = stand_from_spec({**spec, "size_m": 35.0}, n_trees=12, rng=3)
    assert square.n_trees == 12 and square.bounds == (0.0, 0.0, 35.0, 35.0)
    assert square.clutter_kinds == ()  # no clutter spec: no clutter
    # absent DBH / spacing keys take random_stand's defaults
    plain = stand_from_spec({"size_m": 30.0, "n_trees": 10}, rng=4)
    assert _same_stand(plain, random_stand(10, (30.0, 30.0), rng=4))


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ({"layout": "rows", "size_m": 30.0, "n_trees": 5}, "layout 'rows'"),
        (
            {"size_m": 30.0, "n_trees": 5, "dbh_mean": 0.3},
            r"unknown stand spec keys \['dbh_mean'\]",
        ),
        ({"size_m": 30.0}, "no 'n_trees'"),
        ({"size_m": 5.0, "n_trees": 50, "min_spacing_m": 2.0}, "could place only"),
    ],
)
def test_stand_from_spec_rejects_what_it_cannot_build(spec, match):
    with pytest.raises(ConfigError, match=match):
        stand_from_spec(spec, rng=0)


def test_forest_docstring_examples_run():
    import doctest

    import stemmap.sim.forest as forest_mod

    res = doctest.testmod(forest_mod, optionflags=doctest.ELLIPSIS)
    assert res.attempted >= 4 and res.failed == 0
