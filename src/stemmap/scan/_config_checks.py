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
    if cfg.tilt not in ("none", "eq1", "rotation"):
        raise bad("tilt", cfg.tilt, "choose 'none', 'eq1' or 'rotation'")
    if cfg.straight_test not in ("chi2", "ratio"):
        raise bad("straight_test", cfg.straight_test, "choose 'chi2' or 'ratio'")
    if cfg.segmentation not in ("range_jump", "euclidean"):
        raise bad("segmentation", cfg.segmentation, "choose 'range_jump' or 'euclidean'")
    if not cfg.max_jump > 0:
        raise bad("max_jump", cfg.max_jump, "it must be > 0 m")
    if cfg.range_factor < 0:
        raise bad("range_factor", cfg.range_factor, "it must be >= 0")
    if cfg.max_skip < 0:
        raise bad("max_skip", cfg.max_skip, "it must be >= 0 beams")
    if cfg.min_points < 3:
        raise bad("min_points", cfg.min_points, "a circle needs at least 3 returns")
    m = cfg.mixed_end_min_points
    if not (m == 0 or 3 <= m <= cfg.min_points):
        raise bad("mixed_end_min_points", m, "it must be 0 (off) or 3 to min_points returns")
    if not (0.0 <= cfg.residual_floor < 1.0):
        raise bad("residual_floor", cfg.residual_floor, "it must be 0 (off) or in (0, 1)")
    if not (cfg.outline_floor_points == 0 or cfg.outline_floor_points >= 6):
        raise bad(
            "outline_floor_points",
            cfg.outline_floor_points,
            "it must be 0 (off) or >= 6 returns (3 interior residuals over 3 degrees of freedom)",
        )
    if not (cfg.outline_floor_min > 0 and math.isfinite(cfg.outline_floor_min)):
        raise bad("outline_floor_min", cfg.outline_floor_min, "it must be > 0 m and finite")
    if cfg.max_points is not None and cfg.max_points < cfg.min_points:
        raise bad("max_points", cfg.max_points, "it must be >= min_points")
    if cfg.radius_median is not None and not cfg.radius_median > 0:
        raise bad("radius_median", cfg.radius_median, "it must be > 0 m or None")
    if not (cfg.max_width > cfg.min_width >= 0):
        raise bad("max_width", cfg.max_width, "need 0 <= min_width < max_width")
    if not cfg.max_curvature > cfg.min_curvature:
        raise bad("max_curvature", cfg.max_curvature, "it must exceed min_curvature")
    if not cfg.sigma >= 0:
        raise bad("sigma", cfg.sigma, "it must be >= 0 m")
    if not (cfg.sigma_rel >= 0 and math.isfinite(cfg.sigma_rel)):
        raise bad("sigma_rel", cfg.sigma_rel, "it must be >= 0")
    if not (cfg.max_radius > cfg.min_radius >= 0):
        raise bad("max_radius", cfg.max_radius, "need 0 <= min_radius < max_radius")
    if not (cfg.beam_footprint_deg >= 0 and math.isfinite(cfg.beam_footprint_deg)):
        raise bad("beam_footprint_deg", cfg.beam_footprint_deg, "it must be >= 0 degrees")
    if not (0.0 <= cfg.beam_divergence_deg < 20.0):
        raise bad("beam_divergence_deg", cfg.beam_divergence_deg, "it must be in [0, 20) degrees")
    if not (0.0 <= cfg.edge_hit_min <= cfg.edge_hit_max <= 1.0):
        raise bad(
            "edge_hit_min",
            (cfg.edge_hit_min, cfg.edge_hit_max),
            "need 0 <= edge_hit_min <= edge_hit_max <= 1",
        )
    if cfg.fit_residuals not in ("range", "orthogonal"):
        raise bad("fit_residuals", cfg.fit_residuals, "choose 'range' or 'orthogonal'")
    if not (cfg.roughness_max_factor >= 1.0 and math.isfinite(cfg.roughness_max_factor)):
        raise bad("roughness_max_factor", cfg.roughness_max_factor, "it must be >= 1")
    if not (cfg.scan_noise_jump > 0 and math.isfinite(cfg.scan_noise_jump)):
        raise bad("scan_noise_jump", cfg.scan_noise_jump, "it must be > 0 m")
    if not (cfg.scan_noise_surface >= 0 and math.isfinite(cfg.scan_noise_surface)):
        raise bad("scan_noise_surface", cfg.scan_noise_surface, "it must be >= 0 m")
    if cfg.step_noise_pool not in (False, True, "batch"):
        raise bad("step_noise_pool", cfg.step_noise_pool, "choose false, true or 'batch'")
    b = cfg.scan_noise_batch
    if not (b == 0.0 or (b >= 1.0 and math.isfinite(b))):
        raise bad("scan_noise_batch", b, "it must be 0 (off) or >= 1 (a multiple of sigma)")
    if cfg.batch_noise_scale not in ("mad", "biweight"):
        raise bad("batch_noise_scale", cfg.batch_noise_scale, "choose 'mad' or 'biweight'")
    if not (cfg.bark_roughness >= 0 and math.isfinite(cfg.bark_roughness)):
        raise bad("bark_roughness", cfg.bark_roughness, "it must be >= 0 (a fraction)")
    if not (cfg.lobe_roughness >= 0 and math.isfinite(cfg.lobe_roughness)):
        raise bad("lobe_roughness", cfg.lobe_roughness, "it must be >= 0 (a fraction)")
    if not (cfg.lobe_smooth_sigmas > 0 and math.isfinite(cfg.lobe_smooth_sigmas)):
        raise bad("lobe_smooth_sigmas", cfg.lobe_smooth_sigmas, "it must be > 0 (sigmas)")
    f = cfg.rms_noise_from_fit
    if not (f == 0.0 or (f >= 1.0 and math.isfinite(f))):
        raise bad("rms_noise_from_fit", f, "it must be 0 (off) or >= 1 (a multiple of sigma)")
    if not (cfg.rms_own_sigmas > 0 and math.isfinite(cfg.rms_own_sigmas)):
        raise bad("rms_own_sigmas", cfg.rms_own_sigmas, "it must be > 0")
    if not (cfg.lobe_harmonics == 0 or 2 <= cfg.lobe_harmonics <= 8):
        raise bad("lobe_harmonics", cfg.lobe_harmonics, "it must be 0 (off) or 2-8")
    if not (cfg.lobe_prior > 0 and math.isfinite(cfg.lobe_prior)):
        raise bad("lobe_prior", cfg.lobe_prior, "it must be > 0 (a fraction)")
    if not (cfg.lobe_max > 0 and math.isfinite(cfg.lobe_max)):
        raise bad("lobe_max", cfg.lobe_max, "it must be > 0 (a fraction)")
    if not (cfg.corner_depth > 0 and math.isfinite(cfg.corner_depth)):
        raise bad("corner_depth", cfg.corner_depth, "it must be > 0 m")
    if not cfg.corner_depth_convex > 0:
        raise bad("corner_depth_convex", cfg.corner_depth_convex, "it must be > 0 m (inf: off)")
    if not (cfg.corner_sigmas >= 0 and math.isfinite(cfg.corner_sigmas)):
        raise bad("corner_sigmas", cfg.corner_sigmas, "it must be >= 0")
    if cfg.corner_span < 1:
        raise bad("corner_span", cfg.corner_span, "it must be >= 1 return")
    if not cfg.straight_depth_sigmas > 0:
        raise bad("straight_depth_sigmas", cfg.straight_depth_sigmas, "it must be > 0")
    if not cfg.occluded_blend_sigmas > 0:
        raise bad("occluded_blend_sigmas", cfg.occluded_blend_sigmas, "it must be > 0 (inf: off)")
    if not (cfg.gap_sigmas >= 0 and math.isfinite(cfg.gap_sigmas)):
        raise bad("gap_sigmas", cfg.gap_sigmas, "it must be >= 0")
    if not (cfg.gap_ratio >= 0 and math.isfinite(cfg.gap_ratio)):
        raise bad("gap_ratio", cfg.gap_ratio, "it must be >= 0")
    if not cfg.gap_splits >= 0:
        raise bad("gap_splits", cfg.gap_splits, "it must be >= 0 passes")
    if not (cfg.refit_sigmas > 0 and math.isfinite(cfg.refit_sigmas)):
        raise bad("refit_sigmas", cfg.refit_sigmas, "it must be > 0 (robust sigmas)")
    if not (cfg.arc_sigmas > 0 and math.isfinite(cfg.arc_sigmas)):
        raise bad("arc_sigmas", cfg.arc_sigmas, "it must be > 0 (robust sigmas)")
    if not cfg.arc_replace > 1:
        raise bad("arc_replace", cfg.arc_replace, "it must be > 1 (inf: off)")
    if not cfg.behind_sigmas >= 0:
        raise bad("behind_sigmas", cfg.behind_sigmas, "it must be >= 0 (sigmas; inf: off)")
    if not cfg.stub_sigmas >= 0:
        raise bad("stub_sigmas", cfg.stub_sigmas, "it must be >= 0 (sigmas; inf: off)")
    if not (cfg.edge_protrusion >= 0 and math.isfinite(cfg.edge_protrusion)):
        raise bad("edge_protrusion", cfg.edge_protrusion, "it must be >= 0 m and finite")
    if cfg.stub_runs_snoop and not cfg.stub_runs:
        raise bad("stub_runs_snoop", cfg.stub_runs_snoop, "it needs stub_runs")
    if cfg.stub_runs_worst and not cfg.stub_runs:
        raise bad("stub_runs_worst", cfg.stub_runs_worst, "it needs stub_runs")
    if not cfg.max_dbh_sd > 0:
        raise bad("max_dbh_sd", cfg.max_dbh_sd, "it must be > 0 m (inf: off)")
    if not (cfg.dbh_sd_outline >= 0 and math.isfinite(cfg.dbh_sd_outline)):
        raise bad("dbh_sd_outline", cfg.dbh_sd_outline, "it must be >= 0 m and finite")
    for name in (
        "centre_sd_along",
        "centre_sd_across",
        "centre_sd_footprint",
        "centre_sd_across_averaging",
    ):
        if not (getattr(cfg, name) >= 0 and math.isfinite(getattr(cfg, name))):
            raise bad(name, getattr(cfg, name), "it must be >= 0 and finite")
    if not (cfg.dbh_sd_jackknife >= 0 and math.isfinite(cfg.dbh_sd_jackknife)):
        raise bad("dbh_sd_jackknife", cfg.dbh_sd_jackknife, "it must be >= 0 and finite")
    if cfg.stub_runs_inner and not cfg.stub_runs:
        raise bad("stub_runs_inner", cfg.stub_runs_inner, "it needs stub_runs")
    if not (cfg.fit_noise_floor >= 0 and math.isfinite(cfg.fit_noise_floor)):
        raise bad("fit_noise_floor", cfg.fit_noise_floor, "it must be >= 0 m and finite")
    if not (cfg.arc_floor_sigmas > 0 and math.isfinite(cfg.arc_floor_sigmas)):
        raise bad("arc_floor_sigmas", cfg.arc_floor_sigmas, "it must be > 0 (sigmas)")
    if not cfg.arc_tangent_sigmas > 0:
        raise bad("arc_tangent_sigmas", cfg.arc_tangent_sigmas, "it must be > 0 (inf: off)")
    if not cfg.max_rms_sigma > 0:
        raise bad("max_rms_sigma", cfg.max_rms_sigma, "it must be > 0")
    if not cfg.max_radius_width_ratio > 0:
        raise bad("max_radius_width_ratio", cfg.max_radius_width_ratio, "it must be > 0")
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
