"""The ``peel`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.peel.stage`) and its helpers."""
from mmflow.workflow.stages.peel.stage import STAGE

__all__ = ["STAGE"]
