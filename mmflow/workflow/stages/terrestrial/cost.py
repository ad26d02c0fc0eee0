"""The terrestrial stage's cost: a task per channel and time chunk in each of its two phases (the
template's sum, its removal), reading its channel of the chunk."""
from __future__ import annotations

from mmflow.conventions import is_full_stokes
from mmflow.io import run_stores as rs
from mmflow.telescope.beam_factory import JONES_TYPES
from mmflow.workflow.engine.chunking import TIME_CHUNK
from mmflow.workflow.plan.work import Cost, Work


def work(g, cfg):
    n_tchunk = g.n_time_chunks
    four = is_full_stokes(cfg.imaging.stokes) and cfg.beam.type in JONES_TYPES  # the cross hands' coefficients too
    spec = rs.terrestrial_store(n_tchunk, g.n_time, g.n_freq, g.n_bl, cfg.terrestrial.components, g.n_ant, g.n_pol,
                                TIME_CHUNK, cross=four)
    return Work(2 * n_tchunk * g.n_freq, g.vis_task_bytes / g.n_freq, g.chunk_integrations * g.n_bl * g.n_pol, [spec])


COST = Cost(work)
