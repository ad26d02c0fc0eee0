"""The ``stokes`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.stokes.stage`) and its helpers."""
from mmflow.workflow.stages.stokes.stage import STAGE

__all__ = ["STAGE"]
