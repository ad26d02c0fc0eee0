"""The ``calibrate`` stage's settings: the ``calibrate:`` section of a workflow (:class:`CalibrateConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes it from here.
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from mmflow.workflow.config.base import CATALOG_NAMES, Section
from mmflow.workflow.config.calibration import AUTO_CUT, CUT_ALLOWED, BaselineCut


class CalibrateConfig(Section):
    """Gain calibration (Stefcal) against a source model, after the autocorrelation ripple correction."""

    enabled: bool = Field(False, description="Run this stage.")
    sources: list[str] = Field(["Cyg A", "Cas A", "Vir A", "Tau A"], min_length=1, description="Sky model "
                               "(catalogue sources through the beam): by default the four the peel removes, which "
                               "dominate the sky at every hour, so that every solution interval of the day has a "
                               "model that explains its data.", json_schema_extra=CATALOG_NAMES)
    min_baseline_lambda: BaselineCut = Field("auto", description="Use baselines longer than this (wavelengths); "
                                             + AUTO_CUT, json_schema_extra=CUT_ALLOWED)
    solint_s: Optional[float] = Field(3600.0, gt=0, description="Solution interval (s): solutions over the whole "
                                      "data set, which follow a slow drift of the gains (calibrate.smooth_intervals); "
                                      "null: one solution on the track where the sources are highest "
                                      "(calibrate.track_min), applied to the whole data set (the paper's recipe: "
                                      "a drift of d leaves ~d of each peeled source; docs/calibration.md).")
    smooth_intervals: Optional[float] = Field(1.5, gt=0, description="With solint_s: the gains at each integration "
                                              "a local polynomial fit in time (calibrate.smooth_degree; Gaussian "
                                              "kernel of this sigma, in solution intervals: 1.5 h with the default "
                                              "hourly ones) to the intervals' solutions, each weighted by the "
                                              "inverse of the fraction of its data's power the model leaves "
                                              "(gains.zarr unexplained): follows a drift slower than the kernel "
                                              "while averaging down what the unmodelled sky moves in each "
                                              "interval's solution (docs/calibration.md); null: "
                                              "calibrate.interpolate.")
    smooth_degree: int = Field(2, ge=0, le=3, description="With smooth_intervals: the local polynomial's degree "
                               "(0 a weighted mean; 2 follows a curving drift with little bias at this kernel "
                               "width).")
    max_unexplained: float = Field(0.01, gt=0, le=1, description="With smooth_intervals: intervals whose calibrated "
                                   "model leaves more than this fraction of the data's power (the model does not "
                                   "explain them: the bright sources down) are not used, the best interval "
                                   "always; the fit of the nearest used ones holds across them.")
    interpolate: bool = Field(True, description="With solint_s and smooth_intervals null: gains interpolated "
                              "linearly in amplitude and phase between the intervals' centres (a slow drift is "
                              "followed); false: each interval's solution held over it.")
    track_min: float = Field(22.0, gt=0, description="Length of that track (minutes).")
    screen_sources: list[str] = Field(["Cyg A", "Cas A"], description="Of calibrate.sources, the ones given a "
                                      "refractive offset and a scintillation amplitude (mean 1 over the "
                                      "interval, so the flux scale stays the catalogue's) per integration while "
                                      "the gains are solved: the gains then do not absorb the ionosphere's "
                                      "distortion of the brightest sources (docs/calibration.md); [] solves "
                                      "against the catalogue models as they are.", json_schema_extra=CATALOG_NAMES)
    screen_rounds: int = Field(2, ge=1, description="Alternations of gains and screens with screen_sources.")
    measure_flux: list[str] = Field([], description="Of screen_sources, the ones whose flux is measured from "
                                    "the data instead of taken from the catalogue: the others set the flux scale "
                                    "and these get their flux over the catalogue's per interval in gains.zarr "
                                    "(flux_factor). [Cas A] is the paper's recipe: Cyg A on the Baars scale, Cas "
                                    "A (fading ~0.8 %/yr) measured.", json_schema_extra=CATALOG_NAMES)
    tol: float = Field(1e-5, gt=0, lt=1, description="Convergence: ||dg|| / ||g|| below this.")
    max_iter: int = Field(100, ge=1, description="Stefcal iterations at most.")
    damping: Literal["half", "rk4", "none"] = Field("half", description="Stefcal damping of the update.")
    outlier_sigma: Optional[float] = Field(5.0, gt=0, description="Flag antennas whose corrected residuals are "
                                           "outliers at this many sigma (all at once, re-solving until none is left; "
                                           "docs/calibration.md); null: off.")
    max_flagged_fraction: float = Field(0.2, ge=0, le=1, description="Stop, naming the antennas and why, when a "
                                        "solution flags more than this fraction of the antennas that have data "
                                        "(a model that does not describe the data, or that many bad antennas).")
    ripple: bool = Field(True, description="Correct the autocorrelation ripple (HVAC sawtooth) first.")
    ripple_smooth_min: float = Field(45.0, gt=0, description="FWHM of the ripple smoothing kernel (minutes).")
    flag_autos: bool = Field(True, description="After calibration, give the autocorrelations weight 0 in every "
                             "later stage and the imaging (they stay in vis.zarr and still set the radiometer "
                             "noise): they hold the receiver power, so a gain error of 1e-3 leaves more than the "
                             "sky's power in them, and the ripple correction replaces them by their own 45-min "
                             "smooth (docs/calibration.md).")


#: this stage's sections of the workflow schema
SECTIONS = {"calibrate": CalibrateConfig}
