"""The ``models`` stage's settings: the ``models:`` section of a workflow (:class:`ModelsConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes it from here.
"""
from __future__ import annotations

from typing import Optional

from pydantic import Field

from mmflow.workflow.config.base import CATALOG_NAMES, Section


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


#: this stage's sections of the workflow schema
SECTIONS = {"models": ModelsConfig}
