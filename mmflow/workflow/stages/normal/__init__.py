"""The ``normal`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.normal.stage`) and its helpers."""
from mmflow.workflow.stages.normal.stage import STAGE

__all__ = ["STAGE"]
