"""The ingest stage's cost: per time chunk, every channel's visibilities and weights read from the files
and written to ``vis.zarr`` (the units: samples)."""
from __future__ import annotations

from mmflow.workflow.plan.work import Cost, Work, vis_spec


def work(g, cfg):
    units = g.chunk_integrations * g.n_bl * g.n_freq * g.n_pol
    return Work(g.n_time_chunks, g.vis_task_bytes, units, [vis_spec(g)])


COST = Cost(work)
