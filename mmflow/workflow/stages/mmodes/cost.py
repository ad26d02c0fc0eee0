"""The mmodes stage's cost: a task per baseline chunk holding the corrected block of every integration
(complex128 + float64) and its m-modes; with peeling on, the peel's correction of one channel on read
(the subtracted sources' coherencies, five (time, baseline, pol) complex temporaries and the sources'
per-antenna DD gains, read and copied; measured 0.75 GB at 6,628 integrations and 64 antennas, 1.22 GB at
256: docs/planning.md)."""
from __future__ import annotations

from mmflow.conventions import FULL_STOKES, is_full_stokes
from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import COMPLEX128_BYTES, CORRECTED_SAMPLE_BYTES, Cost, Work, halvings

#: complex (time, baseline, pol) temporaries of the peel's correction on read
PEEL_TEMPORARIES = 5
#: bytes per source, antenna and pol of the DD gains read and copied
DD_GAIN_BYTES = 2 * COMPLEX128_BYTES


def work(g, cfg):
    bc = min(g.mmode_chunk, g.n_bl)
    n_sub = len(cfg.peel.sources) if cfg.peel.enabled else 0
    per_time = bc * g.n_freq * g.n_pol * CORRECTED_SAMPLE_BYTES
    if n_sub:
        per_time += (
            bc * COMPLEX128_BYTES * (n_sub + PEEL_TEMPORARIES * g.n_pol) + DD_GAIN_BYTES * n_sub * g.n_ant * g.n_pol
        )
    w = g.n_time * per_time + g.n_split * g.n_freq * (g.mmax + 1) * 2 * bc * COMPLEX128_BYTES
    spec = rs.mmodes_store(g.n_split, g.n_freq, g.mmax, g.n_bl, g.mmode_chunk, {},
                           len(FULL_STOKES) if is_full_stokes(cfg.imaging.stokes) else 0)
    return Work(-(-g.n_bl // bc), w, g.n_time * bc * g.n_freq * g.n_pol, [spec])


COST = Cost(work, shrink="a smaller mmode.baseline_chunk", split=halvings("mmode.baseline_chunk"))
