"""The ``transfer`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.transfer.stage`) and its helpers."""
from mmflow.workflow.stages.transfer.stage import STAGE

__all__ = ["STAGE"]
