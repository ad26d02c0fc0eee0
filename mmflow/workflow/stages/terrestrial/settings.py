"""The ``terrestrial`` stage's settings: the ``terrestrial:`` section of a workflow (:class:`TerrestrialConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes it from here.
"""
from __future__ import annotations


from pydantic import Field

from mmflow.workflow.config.base import Section
from mmflow.workflow.config.calibration import AUTO_CUT, CUT_ALLOWED, BaselineCut


class TerrestrialConfig(Section):
    """Removal of terrestrial signals (cross-talk, near-field RFI) that do not move with the sky."""

    enabled: bool = Field(False, description="Run this stage.")
    components: int = Field(2, ge=1, description="Rank-1 patterns u_k fitted to the zenith-phased average; their "
                            "K^2 Hermitian combinations u_k u_l^H are fitted and subtracted per integration.")
    min_baseline_lambda: BaselineCut = Field("auto", description="Fit amplitudes on baselines longer than this "
                                             "(wavelengths); " + AUTO_CUT, json_schema_extra=CUT_ALLOWED)


#: this stage's sections of the workflow schema
SECTIONS = {"terrestrial": TerrestrialConfig}
