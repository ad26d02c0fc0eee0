"""The models stage's cost: a fit per modelled source and channel over the day's visibilities."""
from __future__ import annotations

from mmflow.workflow.plan.work import Cost, Work


def work(g, cfg):
    n_models = len(cfg.peel.sources) if cfg.models.enabled else 0
    return Work(max(1, n_models) * g.n_freq, g.vis_task_bytes, g.n_time * g.n_bl, [])


COST = Cost(work, shrink="fewer models.sources")
