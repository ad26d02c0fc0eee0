"""The ``clean`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.clean.stage`) and its helpers."""
from mmflow.workflow.stages.clean.stage import STAGE

__all__ = ["STAGE"]
