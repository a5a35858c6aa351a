"""A tree position fused from one trunk's detections, with the outline's share of their centre
error correlated between them (stemmap.slam.uncertainty.fused_positions,
correlated_mean_covariance; stemmap.scan._centre_cov.outline_centre_covs; issue 11, Dec 6,
"Correlated
outline error of a pass" in docs/algorithms/scan-detection.md)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from tests.scan.test_dbh_sd_first_echo import _det
from tests.scan.test_max_dbh_sd import _batch

from stemmap.errors import ConfigError, InputError
from stemmap.scan import DetectorConfig
from stemmap.scan._centre_cov import outline_centre_covs
from stemmap.slam.uncertainty import (
    CENTRE_RHO,
    correlated_mean_covariance,
    fused_diameters,
    fused_positions,
)


def _pass(rng: np.random.Generator, n: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (sensor -> trunk, m), fit covariances and outline covariances of ``n``
    detections of one trunk along a drive-by pass at 4 m offset (sight lines 20-160 deg)."""
    ang = np.radians(np.linspace(20.0, 160.0, n))
    rng_m = 4.0 / np.sin(ang)
    centres = np.column_stack((rng_m * np.cos(ang), rng_m * np.sin(ang)))
    a = rng.normal(size=(n, 2, 2))
    fit = 1e-5 * (a @ a.transpose(0, 2, 1) + 0.5 * np.eye(2))
    shared = outline_centre_covs(centres, DetectorConfig.preset("stemmap", beam_footprint_deg=0.5))
    return centres, fit, shared


def test_rho_zero_is_the_independent_information_fusion(rng: np.random.Generator) -> None:
    _, fit, shared = _pass(rng)
    c = fit + shared
    x = rng.normal(size=(c.shape[0], 2))
    info = np.linalg.inv(c)
    p_ind = np.linalg.inv(info.sum(axis=0))
    for sh in (None, shared, c):
        xy, cov, n = fused_positions(np.zeros(len(c), np.int64), x, c, 1, shared=sh, rho=0.0)
        assert n[0] == len(c)
        assert np.allclose(cov[0], p_ind, rtol=1e-10, atol=0)
        assert np.allclose(xy[0], p_ind @ np.einsum("kij,kj->i", info, x), rtol=1e-12, atol=1e-15)


def test_rho_changes_the_covariance_never_the_position(rng: np.random.Generator) -> None:
    _, fit, shared = _pass(rng)
    c = fit + shared
    x = rng.normal(size=(c.shape[0], 2))
    idx = np.zeros(len(c), np.int64)
    covs = []
    for rho in (0.0, 0.5, 1.0):
        xy, cov, _ = fused_positions(idx, x, c, 1, shared=shared, rho=rho)
        xy0, _, _ = fused_positions(idx, x, c, 1, rho=0.0)
        assert np.array_equal(xy, xy0)
        covs.append(cov[0])
    # more correlation, more stated variance (in every direction), and positive definite
    for lo, hi in itertools.pairwise(covs):
        assert np.all(np.linalg.eigvalsh(hi - lo) >= -1e-18)
        assert np.all(np.linalg.eigvalsh(hi) > 0)


def test_a_fully_shared_error_does_not_shrink_with_n() -> None:
    # n equal detections: independent part A, shared S. Independent fusion states (A + S) / n;
    # with rho = 1 the shared part stays S whatever n (the design effect 1 + (n - 1) rho)
    A = np.array([[4e-5, 1e-5], [1e-5, 2e-5]])
    S = np.array([[1e-4, 0.0], [0.0, 1e-5]])
    for n in (2, 10, 100):
        idx = np.zeros(n, np.int64)
        c = np.broadcast_to(A + S, (n, 2, 2))
        z = np.zeros((n, 2))
        _, one, _ = fused_positions(idx, z, c, 1, shared=np.broadcast_to(S, (n, 2, 2)), rho=1.0)
        assert np.allclose(one[0], A / n + S, rtol=1e-12, atol=0)
        for rho in (0.0, 0.3, 1.0):
            _, p, _ = fused_positions(idx, z, c, 1, shared=np.broadcast_to(S, (n, 2, 2)), rho=rho)
            assert np.allclose(p[0], A / n + S * (1 + (n - 1) * rho) / n, rtol=1e-12, atol=0)


def test_the_stated_covariance_is_the_fused_errors_covariance(rng: np.random.Generator) -> None:
    # the model drawn: e_k = a_k + S_k^(1/2) (sqrt(rho) z + sqrt(1 - rho) y_k), z shared by the
    # pass, a_k, y_k independent; 4000 passes, the sample covariance of the fused error agrees
    # with the stated one to within its sampling error (relative SE of a variance ~
    # sqrt(2 / 4000) = 2.2 %: 10 % tolerance), while rho 0 states less than half of it
    _, fit, shared = _pass(rng)
    n = len(fit)
    c = fit + shared
    idx = np.zeros(n, np.int64)
    ev, V = np.linalg.eigh(shared)
    root = (V * np.sqrt(np.clip(ev, 0, None))[:, None, :]) @ V.transpose(0, 2, 1)
    la = np.linalg.cholesky(fit)
    rho = 0.6
    draws = 4000
    z = rng.normal(size=(draws, 1, 2))
    y = rng.normal(size=(draws, n, 2))
    a = np.einsum("kij,dkj->dki", la, rng.normal(size=(draws, n, 2)))
    s = np.einsum("kij,dkj->dki", root, np.sqrt(rho) * z + np.sqrt(1 - rho) * y)
    e = a + s
    info = np.linalg.inv(c)
    p_ind = np.linalg.inv(info.sum(axis=0))
    W = p_ind @ info
    fused = np.einsum("kij,dkj->di", W, e)
    emp = np.cov(fused.T)
    _, stated, _ = fused_positions(idx, np.zeros((n, 2)), c, 1, shared=shared, rho=rho)
    for v in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([1.0, 1.0]) / np.sqrt(2)):
        assert v @ stated[0] @ v == pytest.approx(v @ emp @ v, rel=0.10)
    assert np.trace(p_ind) < 0.5 * np.trace(emp)


def test_the_scalar_case_is_the_diameters_design_effect(rng: np.random.Generator) -> None:
    # fused_diameters' standard error goes through correlated_mean_covariance: Kish's
    # s^2 (1 + (n - 1) rho) / n with the effective n, as before
    idx = rng.integers(0, 15, 200)
    d = rng.normal(0.3, 0.02, 200)
    sd = rng.uniform(0.005, 0.03, 200)
    for rho in (0.0, 0.4, 1.0):
        _, se, s, n = fused_diameters(idx, d, 15, diameter_std=sd, rho=rho, bias=0.05)
        kish = np.sqrt(s**2 / n * (1 + (n - 1) * rho) + 0.05**2)
        assert np.allclose(se, kish, rtol=1e-12, atol=0, equal_nan=True)


def test_several_trees_and_refusals(rng: np.random.Generator) -> None:
    _, fit, shared = _pass(rng, 6)
    c = fit + shared
    x = rng.normal(size=(6, 2))
    idx = np.array([0, 0, 0, 2, 2, -1])
    xy, cov, n = fused_positions(idx, x, c, 3, shared=shared, rho=1.0)
    assert n.tolist() == [3, 0, 2]
    assert np.all(np.isnan(xy[1])) and np.all(np.isnan(cov[1]))
    one, cov0, _ = fused_positions(np.zeros(3, np.int64), x[:3], c[:3], 1, shared=shared[:3], rho=1)
    assert np.allclose(xy[0], one[0]) and np.allclose(cov[0], cov0[0])
    with pytest.raises(ConfigError, match="rho"):
        fused_positions(idx, x, c, 3, shared=shared, rho=1.5)
    with pytest.raises(ConfigError, match="rho"):
        correlated_mean_covariance(idx, c, c, c, 3, rho=-0.1)
    with pytest.raises(InputError):
        fused_positions(idx[:5], x, c, 3)
    with pytest.raises(InputError, match="n_trees"):
        fused_positions(idx, x, c, 2)


def test_by_default_the_whole_covariance_is_shared_with_centre_rho(
    rng: np.random.Generator,
) -> None:
    # fused_positions(shared=None): every detection's whole covariance correlated with
    # CENTRE_RHO (the real passes' choice); equal detections give C (1 + (n - 1) rho) / n
    assert 0.0 < CENTRE_RHO <= 1.0
    _, fit, shared = _pass(rng)
    c = fit + shared
    x = rng.normal(size=(c.shape[0], 2))
    idx = np.zeros(len(c), np.int64)
    _, dflt, _ = fused_positions(idx, x, c, 1)
    _, same, _ = fused_positions(idx, x, c, 1, shared=c, rho=CENTRE_RHO)
    assert np.array_equal(dflt, same)
    C = np.array([[4e-4, 1e-4], [1e-4, 2e-4]])
    n = 20
    _, p, _ = fused_positions(
        np.zeros(n, np.int64), np.zeros((n, 2)), np.broadcast_to(C, (n, 2, 2)), 1
    )
    assert np.allclose(p[0], C * (1 + (n - 1) * CENTRE_RHO) / n, rtol=1e-12, atol=0)


def test_the_outline_part_is_inside_the_reported_covariance() -> None:
    # a first-echo detection's reported centre block = the fit's at the noise present + the
    # outline part: the remainder is a covariance; an averaging scanner has no outline part
    batch, _ = _batch(2.5)
    obs = _det().detect_batch(batch)
    cfg = _det().config
    assert len(obs) > 0
    part = outline_centre_covs(obs.centers, cfg)
    assert np.all(np.trace(part, axis1=1, axis2=2) > 0)
    rest = obs.covs[:, :2, :2] - part
    assert np.all(np.linalg.eigvalsh(rest) > -1e-15)
    avg = DetectorConfig.preset("stemmap")
    assert avg.beam_footprint_deg == 0
    assert np.array_equal(outline_centre_covs(obs.centers, avg), np.zeros((len(obs), 2, 2)))
