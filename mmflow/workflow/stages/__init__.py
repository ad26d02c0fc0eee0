"""Workflow stages: one module per stage, each defining one ``STAGE`` (a :class:`base.Stage`).

Their order is :data:`mmflow.workflow.pipeline.PIPELINE`; no stage module imports another.
"""
from mmflow.workflow.stages.base import Stage

__all__ = ["Stage"]
