"""The shared footprint-averaging model (stemmap.sim.footprint): the range of a beam split
between a near and a far surface, in the model itself, in the simulator and in the
real-geometry benchmark's virtual scanner."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval.real_slices import virtual_scans
from stemmap.scan.features import mixed_fraction
from stemmap.sim.footprint import footprint_ranges, sub_ray_offsets
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import ScannerModel, simulate_scans

NEAR, FAR = 5.0, 10.0
K = 25
W = math.radians(0.25)


def _expected(f: float, near: float = NEAR, far: float = FAR) -> float:
    """Received-power-weighted range of a footprint with share f on a diffuse surface at
    ``near`` and 1 - f on one at ``far`` (equal reflectance): weights f / near^2 and
    (1 - f) / far^2."""
    return (f / near + (1 - f) / far) / (f / near**2 + (1 - f) / far**2)


@pytest.mark.parametrize("n", [1, 5, 12, 13, 20, 24])
def test_two_surface_beam_is_power_weighted(n):
    f = n / K
    sub = np.array([NEAR] * n + [FAR] * (K - n))
    r = float(footprint_ranges(sub[None, :])[0])
    assert r == pytest.approx(_expected(f), rel=1e-12)
    # between the surfaces, and nearer the near one than the plain area mean (a near surface
    # sends back (far / near)^2 = 4 times the power per unit of footprint)
    assert NEAR < r < f * NEAR + (1 - f) * FAR
    # the detector's mixed-pixel model inverts exactly this range
    assert float(mixed_fraction(r, NEAR, FAR)) == pytest.approx(f, abs=1e-9)


def test_threshold_and_profile_weights():
    sub = np.array([[NEAR, NEAR, np.inf, np.inf], [NEAR, np.inf, np.inf, np.inf]])
    # half the footprint hits: returns under a half threshold, a quarter does not
    r = footprint_ranges(sub, min_share=0.5)
    assert r[0] == pytest.approx(NEAR) and math.isinf(r[1])
    assert np.all(np.isfinite(footprint_ranges(sub, min_share=0.0)))
    assert math.isinf(float(footprint_ranges([[np.inf, np.inf]])[0]))  # nothing hit
    # a profile weight multiplies the received power: 3 : 1 weights on near : far
    r = float(footprint_ranges([[NEAR, FAR]], weight=[3.0, 1.0])[0])
    assert r == pytest.approx((3 / NEAR + 1 / FAR) / (3 / NEAR**2 + 1 / FAR**2))
    with pytest.raises(InputError):
        footprint_ranges([[NEAR, FAR]], weight=[1.0, 0.0])
    with pytest.raises(InputError):
        footprint_ranges([[NEAR, FAR]], min_share=1.5)


def test_sub_ray_offsets_tile_the_footprint():
    off = sub_ray_offsets(W, K)
    # cell centres: spacing W / K, symmetric, the outermost W / (2K) inside the edges
    np.testing.assert_allclose(np.diff(off), W / K)
    assert off[K // 2] == pytest.approx(0.0, abs=1e-18)
    assert off[-1] == pytest.approx(W / 2 - W / (2 * K))


def _edge_stand(edge_bearing: float) -> Stand:
    """A wall at x = FAR behind a flat near panel at x = NEAR covering bearings > edge."""
    y_edge = NEAR * math.tan(edge_bearing)
    segs = [[FAR, -3.0, FAR, 3.0], [NEAR, y_edge, NEAR, 1.0]]
    return Stand(np.zeros((0, 2)), np.zeros(0), segments=segs)


@pytest.mark.parametrize("n", [3, 12, 13, 22])
def test_simulator_edge_beam(n):
    # beam 0 at bearing 0: the panel's edge at the boundary between sub-beams K-n-1 and K-n,
    # so exactly n of the K sub-beams hit it and K - n the wall behind
    edge = -W / 2 + (K - n) * W / K
    m = ScannerModel(
        angle_min=0.0,
        angle_max=math.radians(0.5),
        angle_increment=math.radians(0.5),
        range_noise=0.0,
        beam_divergence=W,
        sub_beams=K,
        min_hit_fraction=0.5,
    )
    batch, _hit, _mixed = simulate_scans(_edge_stand(edge), [[0.0, 0.0, 0.0]], m, rng=0)
    # the sub-beams meet the flat panels at NEAR / cos(theta) (theta <= 0.125 deg): < 0.1 mm
    assert batch.ranges[0, 0] == pytest.approx(_expected(n / K), abs=1e-4)


@pytest.mark.parametrize("n", [3, 12, 13, 22])
def test_real_geometry_scanner_edge_beam(n):
    # the benchmark's virtual scanner on sampled surfaces (1 mm apart, discs of 0.1 mm): the
    # panel's edge in the middle of sub-cell K - n, which it covers in part (a sub-cell
    # returns its nearest point), so again n of K sub-cells see the panel
    edge = -W / 2 + (K - n + 0.5) * W / K
    y_edge = NEAR * math.tan(edge)
    wall = np.column_stack((np.full(6001, FAR), np.linspace(-3.0, 3.0, 6001)))
    ys = np.arange(y_edge, 1.0, 0.001)
    panel = np.column_stack((np.full(ys.size, NEAR), ys))
    xy = np.vstack((wall, panel))
    ranges, _hit = virtual_scans(
        xy,
        np.full(xy.shape[0], -1, dtype=np.int64),
        np.zeros((1, 2)),
        resolution_deg=0.5,
        model="averaging",
        sub_rays=K,
        point_radius=1e-4,
    )
    k0 = 360  # bearing -pi + 360 x 0.5 deg = 0
    assert ranges[0, k0] == pytest.approx(_expected(n / K), abs=1e-3)
