"""Workflow stages: one package per stage (``stages/<name>/``), each defining one ``STAGE`` (a
:class:`base.Stage`), its cost model (``cost.py``) and, where it has settings, ``settings.py``.

:data:`ORDER` is the run order: :data:`mmflow.workflow.pipeline.PIPELINE` is built from it, and the
schema takes the stages' settings sections in it (:func:`mmflow.workflow.config.schema.stage_sections`).
Adding a stage is adding its package and its name here. No stage package imports another.
"""
from mmflow.workflow.stages.base import Stage

#: the stages of an mmflow run, in order (their packages' names)
ORDER = ("simulate", "ingest", "calibrate", "models", "peel", "terrestrial", "mmodes", "transfer", "normal", "solve",
         "stokes", "clean", "products")

__all__ = ["ORDER", "Stage"]
