"""The ``calibrate`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.calibrate.stage`) and its helpers."""
from mmflow.workflow.stages.calibrate.stage import STAGE

__all__ = ["STAGE"]
