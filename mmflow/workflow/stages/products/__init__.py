"""The ``products`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.products.stage`) and its helpers."""
from mmflow.workflow.stages.products.stage import STAGE

__all__ = ["STAGE"]
