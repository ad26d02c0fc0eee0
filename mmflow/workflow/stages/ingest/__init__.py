"""The ``ingest`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.ingest.stage`) and its helpers."""
from mmflow.workflow.stages.ingest.stage import STAGE

__all__ = ["STAGE"]
