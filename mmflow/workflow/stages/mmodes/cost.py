"""The mmodes stage's cost: a task per baseline chunk holding the corrected block of every integration
(complex128 + float64) and its m-modes; with peeling on, the peel's correction of one channel on read
(:func:`mmflow.workflow.plan.work.read_bytes`)."""
from __future__ import annotations

from mmflow.conventions import FULL_STOKES, is_full_stokes
from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import COMPLEX128_BYTES, Cost, Work, halvings, read_bytes


def work(g, cfg):
    bc = min(g.mmode_chunk, g.n_bl)
    w = read_bytes(g, cfg, g.n_time, bc, g.n_freq) + g.n_split * g.n_freq * (g.mmax + 1) * 2 * bc * COMPLEX128_BYTES
    spec = rs.mmodes_store(g.n_split, g.n_freq, g.mmax, g.n_bl, g.mmode_chunk, {},
                           len(FULL_STOKES) if is_full_stokes(cfg.imaging.stokes) else 0)
    return Work(-(-g.n_bl // bc), w, g.n_time * bc * g.n_freq * g.n_pol, [spec])


COST = Cost(work, shrink="a smaller mmode.baseline_chunk", split=halvings("mmode.baseline_chunk"))
