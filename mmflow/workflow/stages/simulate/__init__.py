"""The ``simulate`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.simulate.stage`) and its helpers."""
from mmflow.workflow.stages.simulate.stage import STAGE

__all__ = ["STAGE"]
