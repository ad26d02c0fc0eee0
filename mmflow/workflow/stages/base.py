"""The stage abstraction and the ordered registry of stages.

A stage names the config sections and upstream stages its output depends on (its
fingerprint), the stores it writes, a ``prepare`` step run once by the driver (create
zarr arrays, list chunk keys), a ``task`` run per chunk key on the workers, and an
optional ``finalize`` run by the driver after all tasks.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional


@dataclass
class Stage:
    name: str
    sections: tuple
    upstream: tuple
    outputs: tuple
    prepare: Callable
    task: Callable
    finalize: Optional[Callable] = None
    enabled: Callable = field(default=lambda cfg: True)
    description: str = ""


STAGES: list = []
ORDER = ("simulate", "ingest", "calibrate", "peel", "terrestrial", "mmodes", "transfer", "normal",
         "solve", "clean", "products")


def register(stage):
    STAGES.append(stage)
    STAGES.sort(key=lambda s: ORDER.index(s.name))
    return stage


def all_stages():
    _load()
    return list(STAGES)


def get_stage(name):
    _load()
    for s in STAGES:
        if s.name == name:
            return s
    raise KeyError(name)


def _load():
    # import order is stage order
    from mmflow.workflow.stages import data, imaging, mmodes, normal, slots  # noqa: F401
