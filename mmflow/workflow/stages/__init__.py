"""Workflow stages. Each reads zarr and writes zarr, mapped over chunks (see base.Stage)."""
from mmflow.workflow.stages.base import STAGES, Stage, get_stage

__all__ = ["STAGES", "Stage", "get_stage"]
