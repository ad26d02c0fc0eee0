"""The ``mmodes`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.mmodes.stage`) and its helpers."""
from mmflow.workflow.stages.mmodes.stage import STAGE

__all__ = ["STAGE"]
