"""The ``peel`` stage's settings: the ``peel:`` section of a workflow (:class:`PeelConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes it from here.
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from mmflow.workflow.config.base import CATALOG_NAMES, Section
from mmflow.workflow.config.calibration import AUTO_CUT, CUT_ALLOWED, BaselineCut


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
    tol: float = Field(
        1e-4,
        gt=0,
        lt=1,
        description="Stefcal tolerance of the DD gains (the screen model's: "
        "largest antenna phase change, rad); the solve runs in single precision unless it is below 1e-5.",
    )
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


#: this stage's sections of the workflow schema
SECTIONS = {"peel": PeelConfig}
