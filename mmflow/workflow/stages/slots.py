"""Stages built by other issues (calibration, peeling, terrestrial removal).

They have their place in the graph; disabled, they are skipped and the runner says so.
Enabled before they exist, the run stops with a clear error: a stage is never faked.
"""
from mmflow.errors import InputError
from mmflow.workflow.stages.base import Stage, register


def _unavailable(name):
    def prepare(ctx):
        raise InputError("workflow", f"{name}.enabled", f"the '{name}' stage is not available in this "
                         "version of mmflow", f"set {name}.enabled=false (data are used as they are)")
    return prepare


for _name, _desc, _kind in (("calibrate", "Stefcal per integration", "solve"),
                            ("peel", "direction-dependent peeling", "solve"),
                            ("terrestrial", "terrestrial component removal", "solve")):
    register(Stage(_name, (_name,), (), (), _unavailable(_name), None, kind=_kind,
                   enabled=lambda cfg, n=_name: getattr(cfg, n).enabled, description=_desc))
