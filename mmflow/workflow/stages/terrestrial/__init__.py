"""The ``terrestrial`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.terrestrial.stage`) and its helpers."""
from mmflow.workflow.stages.terrestrial.stage import STAGE

__all__ = ["STAGE"]
