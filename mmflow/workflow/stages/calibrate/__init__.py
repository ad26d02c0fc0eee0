"""The ``calibrate`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.calibrate.stage`, loaded on first use),
its cost model (``cost.py``) and settings (``settings.py``)."""
from mmflow.workflow.stages.base import lazy_stage

__getattr__ = lazy_stage(__name__)
__all__ = ["STAGE"]
