"""The schema sections of the per-integration half: the corrupted simulation, gain calibration,
peeling and terrestrial removal (``docs/calibration.md``)."""
from __future__ import annotations

import math
from typing import Annotated, Literal, Optional, Union

from pydantic import BeforeValidator, Field

from mmflow.workflow.config.base import CATALOG_NAMES, Section
from mmflow.workflow.config.errors import BadValue




def _baseline_cut(v):
    """``auto`` or a number of wavelengths >= 0."""
    if v == "auto":
        return v
    try:
        x = float(v) if not isinstance(v, bool) else math.nan
    except (TypeError, ValueError):
        x = math.nan
    if not (math.isfinite(x) and x >= 0):
        raise BadValue("not auto or a number >= 0", "use auto, or a baseline length in wavelengths >= 0")
    return x


#: a baseline cut (wavelengths) or ``auto`` (:func:`mmflow.calibrate.baselines.auto_min_lambda`)
BaselineCut = Annotated[Union[Literal["auto"], float], BeforeValidator(_baseline_cut)]
CUT_ALLOWED = {"allowed": "auto, or a number >= 0"}
AUTO_CUT = ("'auto' (the default): 15, lowered per channel until every antenna keeps at least half of its "
            "baselines (docs/calibration.md); a cut that leaves an antenna fewer than 3 is refused before work.")


class CorruptConfig(Section):
    """Corruptions of the simulated drift scan (``mmflow.simulate.corrupt``); when enabled the data
    hold XX and YY (and XY, YX for full Stokes), each feed with its own gains, and noise, for calibrate,
    peel and terrestrial to undo."""

    enabled: bool = Field(False, description="Corrupt the simulation (data then hold XX and YY).")
    seed: int = Field(7, ge=0, description="Random seed of the corruptions.")
    gains: bool = Field(True, description="Per-antenna, per-pol complex gains: bandpass and a slow phase drift.")
    sawtooth_db: float = Field(0.1, ge=0, description="HVAC gain sawtooth, peak to peak in power (dB; 0 = off).")
    dd_sources: list[str] = Field(["Cyg A", "Cas A"], description="Sources of sky.sources given direction-"
                                  "dependent gains (ionospheric offsets and scintillation).",
                                  json_schema_extra=CATALOG_NAMES)
    ionosphere_arcmin: float = Field(20.0, ge=0, description="Largest refractive offset at 36.5 MHz (scales nu^-2).")
    scintillation: float = Field(0.2, ge=0, description="Scintillation log-amplitude sigma at 36.5 MHz (nu^-2).")
    crosstalk_jy: float = Field(0.0, ge=0, description="Constant rank-1 cross-talk pattern (Jy; 0 = off).")
    rfi_jy: float = Field(0.0, ge=0, description="Near-field RFI source 10 km west on the horizon (Jy; 0 = off).")
    system_jy: float = Field(0.0, ge=0, description="Receiver and unmodelled background power added to every "
                             "autocorrelation (Jy): it sets the radiometer noise and dominates real autos.")
    leakage: float = Field(0.0, ge=0, lt=1, description="Polarisation leakage (D-terms) of each antenna's feeds: "
                           "|d| uniform in [leakage/5, leakage], random phases (full-Stokes simulations: "
                           "imaging.stokes [I, Q, U, V]; 0 = off).")


class CalibrateConfig(Section):
    """Gain calibration (Stefcal) against a source model, after the autocorrelation ripple correction."""

    enabled: bool = Field(False, description="Run this stage.")
    sources: list[str] = Field(["Cyg A", "Cas A"], min_length=1, description="Sky model (catalogue sources "
                               "through the beam).", json_schema_extra=CATALOG_NAMES)
    min_baseline_lambda: BaselineCut = Field("auto", description="Use baselines longer than this (wavelengths); "
                                             + AUTO_CUT, json_schema_extra=CUT_ALLOWED)
    solint_s: Optional[float] = Field(None, gt=0, description="Solution interval (s); null: one solution on the "
                                      "track where the sources are highest, applied to the whole data set.")
    interpolate: bool = Field(True, description="With solint_s: gains interpolated linearly in amplitude and "
                              "phase between the intervals' centres (a slow drift is followed); false: each "
                              "interval's solution held over it.")
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
                                           "outliers at this many sigma (one at a time); null: off.")
    max_flagged_fraction: float = Field(0.2, ge=0, le=1, description="Stop, naming the antennas and why, when a "
                                        "solution flags more than this fraction of the antennas that have data "
                                        "(a model that does not describe the data, not bad antennas).")
    ripple: bool = Field(True, description="Correct the autocorrelation ripple (HVAC sawtooth) first.")
    ripple_smooth_min: float = Field(45.0, gt=0, description="FWHM of the ripple smoothing kernel (minutes).")
    flag_autos: bool = Field(True, description="After calibration, give the autocorrelations weight 0 in every "
                             "later stage and the imaging (they stay in vis.zarr and still set the radiometer "
                             "noise): they hold the receiver power, so a gain error of 1e-3 leaves more than the "
                             "sky's power in them, and the ripple correction replaces them by their own 45-min "
                             "smooth (docs/calibration.md).")


class PeelConfig(Section):
    """Per-integration peeling (direction-dependent gains) and subtraction of bright sources."""

    enabled: bool = Field(False, description="Run this stage.")
    sources: list[str] = Field(["Cyg A", "Cas A", "Vir A", "Tau A"], min_length=1,
                               description="Sources removed (peeled or subtracted).", json_schema_extra=CATALOG_NAMES)
    peel: list[str] = Field(["Cyg A", "Cas A"], description="Of those, the ones peeled (DD gains) when above "
                            "peel_min_elevation_deg; the others are subtracted with a fitted flux.",
                            json_schema_extra=CATALOG_NAMES)
    model_sources: list[str] = Field([], description="Fainter catalogue sources fitted per integration (a flux "
                                     "scale) together with peel.sources and then left in the data: their flux no "
                                     "longer biases the removed sources' DD gains and fluxes, and the imaged map "
                                     "keeps them (docs/calibration.md).", json_schema_extra=CATALOG_NAMES)
    dd_model: Literal["screen", "antenna"] = Field("screen", description="Direction-dependent gains of a peeled "
                                                  "source per solution. screen: a refractive offset (a phase "
                                                  "gradient across the array) and a scintillation amplitude, 3 "
                                                  "real parameters that absorb little of the sky that is not "
                                                  "modelled. antenna: a free complex gain per antenna (Stefcal), "
                                                  "2 N_ant - 1 parameters, for phase structure that is not a "
                                                  "gradient (arrays larger than the ionospheric patch); on a "
                                                  "compact array they absorb 13-25 % of the unmodelled sky "
                                                  "(docs/calibration.md).")
    peel_min_elevation_deg: float = Field(10.0, ge=0, le=90, description="Peel only above this elevation.")
    peel_min_flux_jy: float = Field(0.0, ge=0, description="Peel only where the source's apparent flux (published "
                                    "flux through the beam) is at least this (Jy); below, it is subtracted with a "
                                    "fitted flux.")
    min_baseline_lambda: BaselineCut = Field("auto", description="Solve on baselines longer than this "
                                             "(wavelengths); " + AUTO_CUT, json_schema_extra=CUT_ALLOWED)
    passes: int = Field(3, ge=1, description="Passes over the sources.")
    tol: float = Field(1e-4, gt=0, lt=1, description="Stefcal tolerance of the DD gains (the screen model's: "
                       "largest antenna phase change, rad); the solve runs in single precision unless it is below 1e-5.")
    max_iter: int = Field(30, ge=1, description="Stefcal iterations per pass.")
    guard: Optional[float] = Field(0.9, gt=0, le=1, description="Subtract instead when peeling removed less than "
                                   "this fraction of the measured flux; null: off.")
    warm_start: bool = Field(False, description="Start each batch's DD gains from the previous batch's last "
                             "solution (fewer iterations) instead of 1; a solution that absorbed part of another "
                             "source is then carried forward (docs/calibration.md).")
    batch: int = Field(16, ge=1, description="Integrations solved together (memory ~ batch x n_ant^2).")
    solint_s: Optional[float] = Field(None, gt=0, description="DD solution interval (s) of the peeled sources: "
                                      "the refractive offset (screen) or the per-antenna gains (antenna) shared "
                                      "over the interval, amplitude per integration (scintillation); rounded to "
                                      "whole integrations, counted from each time chunk's start. null: per "
                                      "integration.")
    fit_positions: bool = Field(False, description="Fit the subtracted sources' positions per integration (matched "
                                "filter within 30 arcmin, on the peeled data with the source put back), then peel "
                                "again with them (stored as DD phase gradients).")


class ModelsConfig(Section):
    """Resolved source models (Gaussian components) fitted from the calibrated data; peel then uses them
    (docs/calibration.md, "Resolved source models")."""

    enabled: bool = Field(False, description="Run this stage (between calibrate and peel).")
    sources: list[str] = Field(["Cyg A", "Cas A"], min_length=1, description="Sources fitted (each among "
                               "peel.sources).", json_schema_extra=CATALOG_NAMES)
    components: dict[str, int] = Field({"Cyg A": 2, "Cas A": 3}, description="Gaussian components per source "
                                       "(1 for a source not listed).")
    size_arcmin: dict[str, float] = Field({"Cyg A": 2.0, "Cas A": 6.0}, description="Largest angular scale of "
                                          "the symmetric start: the components on a ring of radius size / 4, "
                                          "FWHM size / 2 (3 arcmin for a source not listed).")
    min_elevation_deg: float = Field(30.0, ge=0, lt=90, description="Fit on the integrations where the source "
                                     "is above this elevation.")
    min_track_min: float = Field(60.0, gt=0, description="Refuse a source that is above min_elevation_deg for "
                                 "less than this (minutes): the rest of the sky must smear out.")
    max_integrations: int = Field(120, ge=1, description="Of those integrations, use at most this many, evenly "
                                  "spaced (cost ~ integrations x baselines x aperture pixels per evaluation).")
    recentre: bool = Field(True, description="Per integration, move the source back to its catalogued position "
                           "(matched-filter offset, as peel.fit_positions): ionospheric refraction would otherwise "
                           "be fitted as structure.")
    aperture_arcmin: Optional[float] = Field(None, gt=0, description="Radius of the aperture whose residual "
                                             "variance is minimised; null: twice the fringe spacing of the "
                                             "longest baseline used, or twice the start's extent if larger.")
    step_arcmin: Optional[float] = Field(None, gt=0, description="Pixel step in the aperture; null: aperture / 8.")
    maxiter: int = Field(3000, ge=1, description="Nelder-Mead iterations at most.")


class TerrestrialConfig(Section):
    """Removal of terrestrial signals (cross-talk, near-field RFI) that do not move with the sky."""

    enabled: bool = Field(False, description="Run this stage.")
    components: int = Field(2, ge=1, description="Rank-1 patterns u_k fitted to the zenith-phased average; their "
                            "K^2 Hermitian combinations u_k u_l^H are fitted and subtracted per integration.")
    min_baseline_lambda: BaselineCut = Field("auto", description="Fit amplitudes on baselines longer than this "
                                             "(wavelengths); " + AUTO_CUT, json_schema_extra=CUT_ALLOWED)
