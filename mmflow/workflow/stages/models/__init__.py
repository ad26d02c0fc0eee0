"""The ``models`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.models.stage`) and its helpers."""
from mmflow.workflow.stages.models.stage import STAGE

__all__ = ["STAGE"]
