"""The ``solve`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.solve.stage`, loaded on first use),
its cost model (``cost.py``)."""
from mmflow.workflow.stages.base import lazy_stage

__getattr__ = lazy_stage(__name__)
__all__ = ["STAGE"]
