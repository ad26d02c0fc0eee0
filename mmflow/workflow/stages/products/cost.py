"""The products stage's cost: a task per channel holding a few HEALPix maps (float64) of ``npix`` pixels."""
from __future__ import annotations

from mmflow.workflow.plan.work import Cost, Work

#: float64 maps of a channel the plan counts held at once
MAPS = 8


def work(g, cfg):
    return Work(g.n_freq, g.npix * 8.0 * MAPS, g.npix + (g.lmax + 1) ** 2, [])


COST = Cost(work, shrink="a smaller products.nside")
