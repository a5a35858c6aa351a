"""Validation of the detector configuration: the checks of every
:class:`~stemmap.scan.config.DetectorConfig` field when a config is built
(:func:`check_fields`, its ``__post_init__``), the field values of a named preset with its
overrides (:func:`preset_values`, ``DetectorConfig.preset``), and the circle-fit registry both
read (:func:`fit_methods`).

Split from :mod:`stemmap.scan.config`: the fields and what each means are one concept, the rules
a value must meet and the error that names the field another.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from stemmap.errors import ConfigError
from stemmap.scan import circle as _circle
from stemmap.scan._presets import PRESETS

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig

__all__ = ["check_fields", "fit_methods", "preset_values"]


def fit_methods() -> dict[str, Any]:
    """The circle-fit registry of :mod:`stemmap.scan.circle` (read at call time, so fits
    registered later are picked up)."""
    methods: dict[str, Any] = getattr(_circle, "FIT_METHODS", {"kasa": _circle.fit_circle_kasa})
    return methods


def _ge0f(v: Any, c: Any) -> bool:
    return bool(v >= 0 and math.isfinite(v))


def _gt0f(v: Any, c: Any) -> bool:
    return bool(v > 0 and math.isfinite(v))


def _ge0(v: Any, c: Any) -> bool:  # inf allowed (off)
    return bool(v >= 0)


def _gt0(v: Any, c: Any) -> bool:  # inf allowed (off)
    return bool(v > 0)


def _not_below(lo: float) -> _Test:
    return lambda v, c: not v < lo  # NaN passes, as it always has


def _one_of(*choices: Any) -> _Test:
    return lambda v, c: v in choices


def _off_or_ge1(v: Any, c: Any) -> bool:
    return bool(v == 0.0 or (v >= 1.0 and math.isfinite(v)))


def _needs_stub_runs(v: Any, c: Any) -> bool:
    return not v or bool(c.stub_runs)


_Test = Callable[[Any, Any], bool]

#: The checks of :func:`check_fields` after range_min / range_max / fov_deg, in the order they
#: run (the first failing one is reported): field, test of (value, config), what it needs.
_CHECKS: tuple[tuple[str, _Test, str], ...] = (
    ("tilt", _one_of("none", "eq1", "rotation"), "choose 'none', 'eq1' or 'rotation'"),
    ("straight_test", _one_of("chi2", "ratio"), "choose 'chi2' or 'ratio'"),
    ("segmentation", _one_of("range_jump", "euclidean"), "choose 'range_jump' or 'euclidean'"),
    ("max_jump", _gt0, "it must be > 0 m"),
    ("range_factor", _not_below(0), "it must be >= 0"),
    ("max_skip", _not_below(0), "it must be >= 0 beams"),
    ("min_points", _not_below(3), "a circle needs at least 3 returns"),
    (
        "mixed_end_min_points",
        lambda v, c: v == 0 or 3 <= v <= c.min_points,
        "it must be 0 (off) or 3 to min_points returns",
    ),
    ("residual_floor", lambda v, c: 0.0 <= v < 1.0, "it must be 0 (off) or in (0, 1)"),
    (
        "outline_floor_points",
        lambda v, c: v == 0 or v >= 6,
        "it must be 0 (off) or >= 6 returns (3 interior residuals over 3 degrees of freedom)",
    ),
    ("outline_floor_min", _gt0f, "it must be > 0 m and finite"),
    ("max_points", lambda v, c: v is None or not v < c.min_points, "it must be >= min_points"),
    ("radius_median", lambda v, c: v is None or v > 0, "it must be > 0 m or None"),
    ("max_width", lambda v, c: v > c.min_width >= 0, "need 0 <= min_width < max_width"),
    ("max_curvature", lambda v, c: v > c.min_curvature, "it must exceed min_curvature"),
    ("sigma", _ge0, "it must be >= 0 m"),
    ("sigma_rel", _ge0f, "it must be >= 0"),
    ("max_radius", lambda v, c: v > c.min_radius >= 0, "need 0 <= min_radius < max_radius"),
    ("beam_footprint_deg", _ge0f, "it must be >= 0 degrees"),
    ("beam_divergence_deg", lambda v, c: 0.0 <= v < 20.0, "it must be in [0, 20) degrees"),
    (
        "edge_hit_min",
        lambda v, c: 0.0 <= v <= c.edge_hit_max <= 1.0,
        "need 0 <= edge_hit_min <= edge_hit_max <= 1",
    ),
    ("fit_residuals", _one_of("range", "orthogonal"), "choose 'range' or 'orthogonal'"),
    ("roughness_max_factor", lambda v, c: v >= 1.0 and math.isfinite(v), "it must be >= 1"),
    ("scan_noise_jump", _gt0f, "it must be > 0 m"),
    ("scan_noise_surface", _ge0f, "it must be >= 0 m"),
    ("step_noise_pool", _one_of(False, True, "batch"), "choose false, true or 'batch'"),
    ("scan_noise_batch", _off_or_ge1, "it must be 0 (off) or >= 1 (a multiple of sigma)"),
    ("batch_noise_scale", _one_of("mad", "biweight"), "choose 'mad' or 'biweight'"),
    ("bark_roughness", _ge0f, "it must be >= 0 (a fraction)"),
    ("lobe_roughness", _ge0f, "it must be >= 0 (a fraction)"),
    ("lobe_smooth_sigmas", _gt0f, "it must be > 0 (sigmas)"),
    ("rms_noise_from_fit", _off_or_ge1, "it must be 0 (off) or >= 1 (a multiple of sigma)"),
    ("rms_own_sigmas", _gt0f, "it must be > 0"),
    ("lobe_harmonics", lambda v, c: v == 0 or 2 <= v <= 8, "it must be 0 (off) or 2-8"),
    ("lobe_prior", _gt0f, "it must be > 0 (a fraction)"),
    ("lobe_max", _gt0f, "it must be > 0 (a fraction)"),
    ("corner_depth", _gt0f, "it must be > 0 m"),
    ("corner_depth_convex", _gt0, "it must be > 0 m (inf: off)"),
    ("corner_sigmas", _ge0f, "it must be >= 0"),
    ("corner_span", _not_below(1), "it must be >= 1 return"),
    ("straight_depth_sigmas", _gt0, "it must be > 0"),
    ("occluded_blend_sigmas", _gt0, "it must be > 0 (inf: off)"),
    ("gap_sigmas", _ge0f, "it must be >= 0"),
    ("gap_ratio", _ge0f, "it must be >= 0"),
    ("gap_splits", _ge0, "it must be >= 0 passes"),
    ("refit_sigmas", _gt0f, "it must be > 0 (robust sigmas)"),
    ("arc_sigmas", _gt0f, "it must be > 0 (robust sigmas)"),
    ("arc_replace", lambda v, c: v > 1, "it must be > 1 (inf: off)"),
    ("behind_sigmas", _ge0, "it must be >= 0 (sigmas; inf: off)"),
    ("stub_sigmas", _ge0, "it must be >= 0 (sigmas; inf: off)"),
    ("edge_protrusion", _ge0f, "it must be >= 0 m and finite"),
    ("stub_runs_snoop", _needs_stub_runs, "it needs stub_runs"),
    ("stub_runs_worst", _needs_stub_runs, "it needs stub_runs"),
    ("max_dbh_sd", _gt0, "it must be > 0 m (inf: off)"),
    ("dbh_sd_outline", _ge0f, "it must be >= 0 m and finite"),
    ("centre_sd_along", _ge0f, "it must be >= 0 and finite"),
    ("centre_sd_across", _ge0f, "it must be >= 0 and finite"),
    ("centre_sd_footprint", _ge0f, "it must be >= 0 and finite"),
    ("centre_sd_across_averaging", _ge0f, "it must be >= 0 and finite"),
    ("dbh_sd_footprint", _ge0f, "it must be >= 0 and finite"),
    ("dbh_sd_jackknife", _ge0f, "it must be >= 0 and finite"),
    ("stub_runs_inner", _needs_stub_runs, "it needs stub_runs"),
    ("fit_noise_floor", _ge0f, "it must be >= 0 m and finite"),
    ("arc_floor_sigmas", _gt0f, "it must be > 0 (sigmas)"),
    ("arc_tangent_sigmas", _gt0, "it must be > 0 (inf: off)"),
    ("max_rms_sigma", _gt0, "it must be > 0"),
    ("max_radius_width_ratio", _gt0, "it must be > 0"),
)


def check_fields(cfg: DetectorConfig) -> None:
    """Raise :class:`~stemmap.errors.ConfigError` naming the first field of ``cfg`` whose value
    is invalid; ``fov_deg`` is stored as a tuple of floats (``cfg`` is frozen: set in place)."""

    def bad(field: str, value: Any, need: str) -> ConfigError:
        return ConfigError(f"detector config {cfg.name!r}: {field} = {value!r} is invalid; {need}.")

    if cfg.range_min is not None and not cfg.range_min >= 0:
        raise bad("range_min", cfg.range_min, "it must be >= 0 m")
    if cfg.range_max is not None and not cfg.range_max > (cfg.range_min or 0.0):
        raise bad("range_max", cfg.range_max, "it must exceed range_min")
    if cfg.fov_deg is not None:
        if len(cfg.fov_deg) != 2 or not cfg.fov_deg[1] > cfg.fov_deg[0]:
            raise bad("fov_deg", cfg.fov_deg, "give (lo, hi) degrees with hi > lo")
        object.__setattr__(cfg, "fov_deg", (float(cfg.fov_deg[0]), float(cfg.fov_deg[1])))
    for field, ok, need in _CHECKS:
        value = getattr(cfg, field)
        if not ok(value, cfg):
            shown = (value, cfg.edge_hit_max) if field == "edge_hit_min" else value
            raise bad(field, shown, need)
    if cfg.fit_method not in fit_methods():
        raise bad(
            "fit_method",
            cfg.fit_method,
            f"choose one of {sorted(fit_methods())} (registered circle fits)",
        )


def preset_values(name: str, overrides: dict[str, Any], known: set[str]) -> dict[str, Any]:
    """The field values of preset ``name`` (see :data:`~stemmap.scan._presets.PRESETS`) with
    ``overrides`` (each one of the ``known`` field names): what ``DetectorConfig.preset``
    builds its config from."""
    if name == "ohman2007":
        raise ConfigError(
            "preset 'ohman2007' does not exist: Öhman et al. (2007) publish no laser "
            "segmentation or filtering parameters (only the 0.25/0.5/1 deg scanner modes and "
            "the diameter error vs range); use 'zheng2012' or 'stemmap' with "
            "fit_method of your choice."
        )
    try:
        base = PRESETS[name]
    except KeyError:
        raise ConfigError(
            f"unknown detector preset {name!r}; choose one of {sorted(PRESETS)}."
        ) from None
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ConfigError(f"unknown detector config field(s) {unknown}; known: {sorted(known)}.")
    values = {**base, "name": name, **overrides}
    if values["fit_method"] not in fit_methods() and "fit_method" not in overrides:
        raise ConfigError(
            f"preset {name!r} needs circle fit {values['fit_method']!r}, which is not "
            f"registered (available: {sorted(fit_methods())}); pass fit_method=..."
        )
    return values
