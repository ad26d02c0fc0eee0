"""The ``simulate`` stage: :data:`STAGE` (:mod:`mmflow.workflow.stages.simulate.stage`), its cost model
(``cost.py``).

``STAGE`` is imported on first use, so that the schema can take a stage's settings without importing the
stage (which imports the schema).
"""


def __getattr__(name):
    if name == "STAGE":
        from mmflow.workflow.stages.simulate.stage import STAGE  # deferred: the stage imports the schema

        return STAGE
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["STAGE"]
