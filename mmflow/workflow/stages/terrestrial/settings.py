"""The ``terrestrial`` stage's settings: the ``terrestrial:`` section of a workflow (:class:`TerrestrialConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes it from here.
"""
from __future__ import annotations


from typing import Literal

from pydantic import Field

from mmflow.workflow.config.base import Section
from mmflow.workflow.config.calibration import AUTO_CUT, CUT_ALLOWED, BaselineCut


class TerrestrialConfig(Section):
    """Removal of terrestrial signals (cross-talk, near-field RFI) that do not move with the sky."""

    enabled: bool = Field(False, description="Run this stage.")
    components: int = Field(2, ge=1, description="Rank-1 patterns u_k fitted to the zenith-phased average; their "
                            "K^2 Hermitian combinations u_k u_l^H are fitted and subtracted per integration.")
    amplitudes: Literal["auto", "per_integration", "constant"] = Field(
        "auto", description="The templates' amplitudes: fitted and subtracted per integration (follows flickering "
        "RFI, but takes whatever of the sky lies along the templates), constant (each one's mean over the day: the "
        "stationary part only, which lives at m = 0), or auto: per integration unless that would take more than "
        "5 % of the map peak of a source at some declination (a small array whose templates resemble the sky), "
        "decided per channel (terrestrial.zarr: sky_loss, per_integration; docs/calibration.md).")
    min_baseline_lambda: BaselineCut = Field("auto", description="Fit amplitudes on baselines longer than this "
                                             "(wavelengths); " + AUTO_CUT, json_schema_extra=CUT_ALLOWED)


#: this stage's sections of the workflow schema
SECTIONS = {"terrestrial": TerrestrialConfig}
