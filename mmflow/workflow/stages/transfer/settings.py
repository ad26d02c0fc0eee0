"""The ``transfer`` stage's settings: the ``transfer:`` section of a workflow (:class:`TransferConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes it from here.
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from mmflow.workflow.config.base import Section


class TransferConfig(Section):
    """Transfer matrices and normal equations."""

    mode: Literal["normal", "store"] = Field("normal", description="'normal': stream G_m; 'store': also write B_m.")
    dtype: Literal["float32", "float64"] = Field("float64", description="Precision of the transfer matrices.")
    baseline_chunk: int = Field(32, ge=1, description="Baselines per transfer chunk of the longest baselines "
                                "(memory ~ chunk * lmax^2 * 16 B); shorter baselines share chunks up to 16x larger "
                                "within the same memory.")
    per_baseline_lmax: bool = Field(True, description="Cut each baseline's rows at its own band limit.")
    m_block: int = Field(16, ge=1, description="m values per reduction / solve task.")
    groups: int = Field(8, ge=1, description="Baseline groups of the transfer stage: tasks per frequency, and "
                        "partial normal equations kept on disk (each ~ the Gram's size). Set >= the cluster's worker "
                        "threads for parallelism. Results never depend on the cluster.")
    noise_weighting: bool = Field(True, description="Weight baselines by 1/variance in G_m (minimum variance).")


#: this stage's sections of the workflow schema
SECTIONS = {"transfer": TransferConfig}
