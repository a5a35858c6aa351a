"""Parameters of our cloud stem detector (:class:`StemConfig`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stemmap.cloud.ground import DEFAULT_MAX_MEMORY
from stemmap.cloud.quantisation import MAX_COORDINATE_STEP
from stemmap.cloud.result import BREAST_HEIGHT
from stemmap.errors import ConfigError

__all__ = ["StemConfig"]


@dataclass(frozen=True)
class StemConfig:
    """Parameters of our stem detector. Defaults need no per-cloud tuning.

    Attributes
    ----------
    breast_height : float, metres (1.3)
    slice_centers : tuple of float, metres above ground
        Centres of the horizontal slices fitted per stem; the band they span is clustered.
    slice_thickness : float, metres
    ground_cell : float, metres -- ground raster cell (1.0)
    min_diameter, max_diameter : float, metres -- plausible DBH window (0.04, 1.5)
    min_arc_deg : float -- minimum angular coverage of a slice fit (one side of a trunk seen
        from one scanner covers up to ~180 degrees; 30 keeps partly occluded trunks, whose
        DBH is then less certain and whose quality is scaled by arc / 120 degrees)
    min_slice_points : int -- minimum inliers of a slice fit
    min_slices : int -- slices that must pass for a stem (1 for a pre-cut slice cloud)
    min_vertical_extent : float, metres -- the passing slices' centres must span at least this
        (a stem is vertical; bushes and branch stubs are not); ignored for a pre-cut slice
    slices_per_spacing : float -- a slice is at least this many measured point spacings thick;
        sparse clouds get fewer, thicker slices over the same band (0 disables)
    thin_remeasure : bool -- a stem found on a band thickened to at most
        ``thin_remeasure_max_slices`` slices -- in the first round, by the tighter refits, or
        chosen by the single-tree ladder -- is measured again on the default thin slices
        about its circle (:func:`~stemmap.cloud.slicestem._thin_slice_stem`); the thin
        measurement replaces the thick one when it is the better one
        (``thin_remeasure_by``)
    thin_remeasure_by : str -- when the thin re-measure replaces the thick measurement:
        ``"slices"`` (more thin slices agree than thick ones did, as before) or ``"error"``
        (its DBH standard deviation with the section term at its model weight -- fit noise
        plus the kept slices' scatter about the stem's local profile,
        :func:`~stemmap.cloud.dbhsd.dbh_variance` at ``dbh_sd_scatter`` = 1 -- is smaller
        than the thick measurement's). ``"error"`` since Dec 6 (chosen in 6 of 7 folds of
        the cloud LOO, held out never worse): docs/algorithms/cloud.md "Thinned clouds: the
        re-measure by its error"
    thin_remeasure_max_slices : int -- the thin re-measure applies to bands thickened to at
        most this many slices (4, ``min_slices`` + 1; a thickened band has 3-5 slices; partly
        chosen on real clouds, docs/algorithms/cloud.md "Plots at lower density (Dec 4)" and
        "Leave-one-dataset-out check of the cloud defaults")
    max_taper : float -- largest plausible |d radius / d height| in the band, m/m; a candidate
        whose slice radii change faster is not a stem
    residual_factor : float -- a slice fit passes if its RMS is below ``residual_factor`` times
        the cloud's noise floor (median slice RMS) -- measured, not tuned
    cluster_cell_factor : float -- grid clustering cell = this x the 90th-percentile 2D point
        spacing in the band (measured)
    spacing : float, optional -- use this point spacing (metres) instead of measuring it on
        the band (90th percentile of the 3D nearest-neighbour distance); the spacing sets the
        clustering cell, the slice thickness of sparse clouds and the RANSAC tolerance
    noise_floor : float, optional -- use this slice-fit noise floor (metres) instead of the
        median RMS of the band's plausible slice fits. The tile engine measures spacing and
        noise floor once per catalog and passes both to every chunk, so a chunk's thresholds
        are those of the whole cloud (docs/algorithms/engine.md)
    grid_origin : (x, y), optional -- anchor the clustering and vertical-filter grids at this
        point (cell edges at origin + k x cell) instead of at the band's minimum; the tile
        engine sets one for the whole catalog so every chunk uses the same cells
    filter_origin : (x, y), optional -- anchor of the vertical-filter grid when it differs
        from ``grid_origin`` (None: ``grid_origin``). A run without either anchors the filter
        at the band's minimum and the clustering at the filtered points' minimum; the tile
        engine passes both minima of the whole catalog when its pilot region covers it, so a
        chunk's cells are a single run's (docs/algorithms/engine.md)
    ground_extent : (xmin, ymin, xmax, ymax), optional -- the ground raster spans (at least)
        the cells of this box, not only the occupied cells' bounding box; the tile engine sets
        the catalog's box and each chunk builds the part its buffer covers
        (``prepare_cloud(ground_window=)``), so the ground near a data edge inside the
        catalog (a corner) does not depend on where chunks are cut
    fit_method : str -- circle fit (``scan.circle.FIT_METHODS``); "ours" is the robust
        geometric fit
    estimate_height : bool -- also estimate stem height (highest point within 1 m of the axis)
    slice_mode : "auto" | "always" | "never" -- treat the cloud as an already cut, height-
        normalised slice (auto: when its z extent is below 1 m)
    pooled_fallback : bool -- clusters the per-slice fits reject get one tilted-cylinder fit
        over the whole band with stricter tests (:func:`~stemmap.cloud.pooled._pooled_stems`):
        trunks with few returns per slice (partly occluded, sparse clouds)
    tighter_refits : bool -- clusters the per-stem tests reject get their slices refitted with
        halved RANSAC tolerances down to 5 mm (:func:`~stemmap.cloud._ladder._tighter_refits`):
        a sparse single tree whose slices all fit its branch whorls
    core_refits : bool -- a slice circle with a stem's worth of returns inside its disc is
        refitted to the stem inside it (a trunk is opaque;
        :func:`~stemmap.cloud.slicefit._opaque_core_refits`): a noisy spruce's circles through
        bark and branch stubs
    ransac_lo : bool -- the slice fits' RANSAC start scores circles by MSAC and locally
        optimises the best hypotheses of every batch (LO-RANSAC;
        :func:`~stemmap.cloud.slicefit._ransac_circle`): the start no longer depends on which
        minimal samples were drawn (docs/algorithms/cloud.md, "RANSAC draws")
    ransac_seed : int -- the slice fits' RANSAC draws: 0 (the default) seeds each segment's
        generator by its point count alone, another value (>= 0) by (seed, count)
        (:func:`~stemmap.cloud.slicefit._segment_rng`): other, equally valid draws, for
        measuring how much a result depends on them (benchmarks/cloud_ransac_seeds.py). Part
        of the configuration, so a tile run's manifest tells seeds apart (``--resume``)
    slice_fit_window : float -- the slice fits keep the points within this many RANSAC
        tolerances of a RANSAC start and trim residuals beyond this many robust sigmas
        (1.4826 MAD) (:func:`~stemmap.cloud.slicefit._fit_segments`; 3). Narrower keeps a
        noisy stem's branch stubs out of its fit (docs/algorithms/cloud.md, "RANSAC draws:
        the noisy spruce")
    slice_stub_trim : float -- 0 (off), or the slice fits' trim takes its robust sigma
        (1.4826 MAD) from the residuals inside the circle only, drops the points more than
        this many of those sigmas outside it (and, as before, more than
        ``slice_fit_window`` of them either side), and trims and refits three times
        (:func:`~stemmap.cloud.slicefit._fit_segments`): branch stubs and needles lie outside
        the bark only, the noise on both sides, so the stubs no longer widen the trim that
        should remove them (docs/algorithms/cloud.md, "The noisy spruce: a trim scaled by the
        inside half")
    slice_stub_surface : bool -- with ``slice_stub_trim`` (required), the stub trim's outside
        bound is measured from the local surface: the median residual of the point's angular
        sector (~10 cm of arc), where that lies outside the circle
        (:func:`~stemmap.cloud.stubtrim.trim_keep`). A branch stub is a minority of its
        sector's returns and is still trimmed; a fork's crotch or a lobe moves the whole
        sector and is kept (docs/algorithms/cloud.md, "The noisy spruce: a stub trim
        measured from the local surface"; default off)
    single_tree_ladder : bool -- with a single candidate cluster (a single-tree cloud, whose
        noise floor is its own), the stem is chosen among the first round's and the tighter
        refits' at every tolerance by support (:func:`~stemmap.cloud._ladder.
        _single_tree_stem`), not the first tolerance that gives one
    continues_above : bool -- a stem whose agreeing slices end below the band's top slice
        needs at least one band return about its circle above them (a trunk goes on above
        the band; a shrub, a sapling's clump or stacked debris ends:
        :func:`~stemmap.cloud.slicestem._ends_in_band`); the pooled fit has its own,
        stricter top-slice test
    thick_dbh_slice : bool -- in a plot (noise floor pooled over its stems) whose band was
        thickened to at most ``thin_remeasure_max_slices`` slices, a stem measured on the
        thick slices takes its radius from the kept slice that holds the measurement height,
        not from the Theil-Sen line through three or four radii, whose outer slices span the
        root flare (0.8-1.2 m) and the crown base (1.6-2.0 m); the centre, lean and taper test
        stay the line's (:func:`~stemmap.cloud.slicestem._stem_at`; docs/algorithms/cloud.md
        "Sparse plots: DBH from the slice at breast height")
    thin_refit_points : bool -- in a plot (noise floor pooled over its stems) whose band was
        thickened, the guided refits of the tighter refits on the default thin slices (the
        annulus fits about the circle two agreeing thin slices predict) need
        ``min_slice_points`` x thin / thick inliers (at least 5) instead of
        ``min_slice_points``: a thin slice holds that fraction of a thick one's returns on the
        same stem (:func:`~stemmap.cloud.slicestem.thin_slice_points`). The thin re-measure
        of a stem already found keeps ``min_slice_points``. Off: docs/algorithms/cloud.md
        "Sparse plots: thin-slice counts from the density"
    density_slice_points : bool -- slice-fit inlier counts follow the cloud's measured
        spacing (:func:`~stemmap.cloud.band.density_slice_points`): ``slices_per_spacing``
        spacings is the thickness at which a slice holds ``min_slice_points`` returns on a
        stem's side (:func:`~stemmap.cloud.band._adapt_slices`); a slice thinner than that
        holds thickness / that share, and is asked for ``min_slice_points`` x that share (at
        least 5, never more than ``min_slice_points``). It applies to the band's slices when
        the band is held at three slices thinner than the design (spacing > 100 mm: 7 at
        128 mm) -- their fits, guided refits and tighter refits; the pooled cylinder keeps the
        dense count and the clusters it took before -- and, in a plot, to the thin ladder's
        guided refits (0.2 m slices: 5 at 93 mm, as ``thin_refit_points``). The thin
        re-measure of a found stem keeps ``min_slice_points``. On since Dec 6 (chosen in every
        fold of the cloud LOO, held out 238 vs 236 cells): docs/algorithms/cloud.md "Thinned
        plots and trees: slice counts from the measured spacing"
    consensus_floor : bool -- in a plot (noise floor pooled over its stems), the radius
        consensus of a stem's slices weighs each slice fit by inliers / max(RMS, noise
        floor)^2 instead of inliers / RMS^2: a fit smoother than the cloud's floor (a few
        clutter points on a circle) does not outvote the stem's slices
        (:func:`~stemmap.cloud.slicestem._consensus_weights`). Off: docs/algorithms/cloud.md
        "Sparse plots: the consensus weight floored at the noise"
    consensus_radius_se : bool -- the radius consensus of a stem's slices weighs each slice by
        its radius's own inverse variance (from the fit's covariance: arc, inliers, RMS)
        instead of inliers / RMS^2 and takes the weighted median (in a plot the RMS in the
        covariance floored at the pooled noise floor;
        :func:`~stemmap.cloud.slicestem._radius_consensus`). Off:
        docs/algorithms/cloud.md "Short arcs in the radius consensus"
    guided_taper : bool -- a guided refit (the annulus fit of a slice that disagreed, about
        the circle the agreeing slices predict) is kept only when the Theil-Sen line through
        the agreeing slices' radii and the refits kept so far stays within ``max_taper``
        (:func:`~stemmap.cloud.slicestem._taper_checked`): a refit on a root flare is left
        out instead of failing the whole stem's taper test. Off: docs/algorithms/cloud.md
        "Short arcs in the radius consensus"
    ladder_found_rms : bool -- the single-tree ladder's fair-support test (a smaller stem
        fitted at a tolerance not below the kept stem's RMS may win on support,
        :func:`~stemmap.cloud._ladder._single_tree_stem`) takes the RMS of the slice fits
        the kept stem was found with, not that of its thin re-measure (annulus fits about a
        known circle, whose RMS is no RANSAC residual; docs/algorithms/cloud.md "aRchi
        Tree_1 at 20 %: where its DBH moves"). On since Dec 6: a fix of the test's meaning
        that changes no shipped cloud (docs "ladder_found_rms is the default")
    ladder_by : str -- when a smaller stem of the single-tree ladder may replace the kept one
        on support (:func:`~stemmap.cloud._ladder._single_tree_stem`): ``"tolerance"`` (it was
        fitted at a RANSAC tolerance not below the kept stem's RMS, the fair-support test, as
        before) or ``"error"`` (its DBH standard deviation with the section term at its model
        weight, as ``thin_remeasure_by = "error"`` reads it, is smaller than the kept
        stem's, and the two DBHs agree within ``ladder_agree_z`` standard deviations of
        their difference: a smaller circle carved out of rough bark is a consistent inner
        surface, its error no larger). Default ``"tolerance"``: issue 11,
        docs/algorithms/cloud.md "The single-tree ladder by its error"
    ladder_agree_z : float -- > 0, with ``ladder_by = "error"``: how many standard deviations
        of their difference (the two section-aware DBH errors taken as independent) a ladder
        stem's DBH may lie from the kept stem's (2, about 95 % of normal differences)
    dbh_from : str -- where a stem's radius at the measurement height comes from, when three
        or more kept slices span >= 0.3 m: ``"line"`` (the Theil-Sen line through the kept
        slices' radii, as before), ``"slice"`` (the kept slice that holds the measurement
        height) or ``"median"`` (the median of the kept slices within one slice thickness of
        it, at least three; else the line). The centre, lean correction and taper test stay
        the line's (:mod:`~stemmap.cloud.bhradius`). ``"median"`` since Dec 6 (the section at
        breast height, as a tape measures it; docs/algorithms/cloud.md "Breast-height DBH,
        stage by stage" and "The median at breast height is the default")
    dbh_sd_scatter : float -- k >= 0, the weight of the section term in a stem's stated DBH
        variance (:func:`~stemmap.cloud.dbhsd.dbh_variance`): a real stem's section differs
        from one slice to the next by more than its fits say, and the variance is built from
        the fit noise plus ``k^2 tau^2`` (tau^2: the kept slices' local scatter beyond their
        fit noise; a pre-cut slice's: its sub-slices' scatter about their mean) carried
        through the estimate against the section at the measurement height (the median of
        the slices about it by fixed normal draws). 0 (off): the fit noise alone -- for the
        median, through the exact median of the slices about their line (not pi / 2).
        Changes ``diameter_std`` only, never a DBH. Off: docs/algorithms/cloud.md "The DBH
        std from its parts" (k = 1, the model's value, brings every ring-referenced cloud's
        median |z| toward 0.67 but held out the choice over-covers treels pine_plot)
    axis_fallback : bool -- sparse clusters that neither the per-slice path nor the pooled
        fit made a stem get one shared-axis ring-stack fit with a taper prior and a gate on
        its DBH standard error (:func:`~stemmap.cloud.axisfit._axis_stems`). Off: on the real
        clouds' leave-one-dataset-out check it changes no cell (docs/algorithms/cloud.md
        "Sparse stems: one fit over the band")
    axis_reach : bool -- the shared-axis fit also uses the returns at 0.5-3.0 m outside the
        band (:data:`~stemmap.cloud.axisfit.AXIS_RANGE`; read from files, in-memory clouds
        and the tile engine's chunks)
    sparse_tall_fit : bool -- sparse clusters (fullest band slice < 3 x ``min_slice_points``
        returns) that no other path made a stem are measured by one leaning ring stack with a
        taper prior over 0.5-3.0 m: the axis from the cluster's band returns, the range's
        returns about it gathered and refitted twice, the shared-axis fit's tests over 6 bins
        and its gate on the DBH standard error (:func:`~stemmap.cloud.sparsereach.
        _sparse_tall_stems`); the stem's ``dbh_rule`` names the range. Off:
        docs/algorithms/cloud.md "Sparse plots: one ring stack over 0.5-3.0 m"
    max_memory : float, bytes -- budget for the run's rasters (ground grid, clustering grid);
        a cloud that would need more is refused with an InputError naming the raster (4 GB)
    max_coordinate_step : float or None, metres -- a cloud whose x or y coordinates near the
        stems are rounded to a coarser step (float32 at UTM values, a 0.1 m LAS scale) is
        refused with an InputError saying why and how to re-export
        (:mod:`~stemmap.cloud.quantisation`, 0.02 m; None: measure anyway)
    """

    breast_height: float = BREAST_HEIGHT
    slice_centers: tuple[float, ...] = (0.9, 1.1, 1.3, 1.5, 1.7, 1.9)
    slice_thickness: float = 0.2
    ground_cell: float = 1.0
    min_diameter: float = 0.04
    max_diameter: float = 1.5
    min_arc_deg: float = 30.0
    min_slice_points: int = 8
    min_slices: int = 3
    residual_factor: float = 3.0
    cluster_cell_factor: float = 2.0
    spacing: float | None = None
    noise_floor: float | None = None
    grid_origin: tuple[float, float] | None = None
    filter_origin: tuple[float, float] | None = None
    ground_extent: tuple[float, float, float, float] | None = None
    fit_method: str = "ours"
    estimate_height: bool = False
    slice_mode: str = "auto"
    min_vertical_extent: float = 0.4
    slices_per_spacing: float = 4.0
    thin_remeasure: bool = True
    thin_remeasure_max_slices: int = 4
    thin_remeasure_by: str = "error"
    max_taper: float = 0.05
    pooled_fallback: bool = True
    tighter_refits: bool = True
    core_refits: bool = True
    ransac_lo: bool = True
    ransac_seed: int = 0
    slice_fit_window: float = 3.0
    slice_stub_trim: float = 0.0
    slice_stub_surface: bool = False
    single_tree_ladder: bool = True
    continues_above: bool = True
    thick_dbh_slice: bool = True
    thin_refit_points: bool = False
    density_slice_points: bool = True
    consensus_floor: bool = False
    consensus_radius_se: bool = False
    guided_taper: bool = False
    ladder_found_rms: bool = True
    ladder_by: str = "tolerance"
    ladder_agree_z: float = 2.0
    dbh_from: str = "median"
    dbh_sd_scatter: float = 0.0
    axis_fallback: bool = False
    axis_reach: bool = True
    sparse_tall_fit: bool = False
    max_memory: float = DEFAULT_MAX_MEMORY
    max_coordinate_step: float | None = MAX_COORDINATE_STEP

    def __post_init__(self) -> None:
        if not self.slice_centers or self.slice_thickness <= 0:
            raise ConfigError("need at least one slice centre and slice_thickness > 0 m.")
        if not 0 < self.min_diameter < self.max_diameter:
            raise ConfigError(
                f"need 0 < min_diameter < max_diameter, got {self.min_diameter}, "
                f"{self.max_diameter}."
            )
        if self.slice_mode not in ("auto", "always", "never"):
            raise ConfigError(f"slice_mode must be auto, always or never, got {self.slice_mode!r}.")
        if not self.max_memory > 0:
            raise ConfigError(f"max_memory must be > 0 bytes, got {self.max_memory}.")
        if self.spacing is not None and not self.spacing > 0:
            raise ConfigError(f"spacing must be > 0 m, got {self.spacing}.")
        if self.noise_floor is not None and not self.noise_floor > 0:
            raise ConfigError(f"noise_floor must be > 0 m, got {self.noise_floor}.")
        if not (isinstance(self.ransac_seed, (int, np.integer)) and self.ransac_seed >= 0):
            raise ConfigError(f"ransac_seed must be an integer >= 0, got {self.ransac_seed!r}.")
        if self.dbh_from not in ("line", "slice", "median"):
            raise ConfigError(f"dbh_from must be line, slice or median, got {self.dbh_from!r}.")
        if self.thin_remeasure_by not in ("slices", "error"):
            raise ConfigError(
                f"thin_remeasure_by must be slices or error, got {self.thin_remeasure_by!r}."
            )
        if self.ladder_by not in ("tolerance", "error"):
            raise ConfigError(f"ladder_by must be tolerance or error, got {self.ladder_by!r}.")
        if not self.ladder_agree_z > 0:
            raise ConfigError(f"ladder_agree_z must be > 0, got {self.ladder_agree_z}.")
        if not self.dbh_sd_scatter >= 0:
            raise ConfigError(f"dbh_sd_scatter must be >= 0 (0: off), got {self.dbh_sd_scatter}.")
        if not self.slice_fit_window > 0:
            raise ConfigError(f"slice_fit_window must be > 0, got {self.slice_fit_window}.")
        if not self.slice_stub_trim >= 0:
            raise ConfigError(f"slice_stub_trim must be >= 0 (0: off), got {self.slice_stub_trim}.")
        if self.slice_stub_surface and not self.slice_stub_trim > 0:
            raise ConfigError("slice_stub_surface measures the stub trim: set slice_stub_trim > 0.")
        if self.max_coordinate_step is not None and not self.max_coordinate_step > 0:
            raise ConfigError(
                f"max_coordinate_step must be > 0 m (or None), got {self.max_coordinate_step}."
            )

    @property
    def band(self) -> tuple[float, float]:
        c = np.asarray(self.slice_centers)
        return float(c.min() - self.slice_thickness / 2), float(c.max() + self.slice_thickness / 2)
