"""The ``solve`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.solve.stage`) and its helpers."""
from mmflow.workflow.stages.solve.stage import STAGE

__all__ = ["STAGE"]
