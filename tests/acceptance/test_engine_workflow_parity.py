"""One piece of code per computation: the workflow's transfer/normal/solve stages give the
engine's normal equations and alm bit for bit (float32 transfer, complex64 Grams)."""
import numpy as np
import pytest
import zarr

from mmflow.conventions import m_slice
from mmflow.io.run_stores import STORES
from mmflow.imaging.solvers import solve_alm
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.mmode.noise import relative_weights
from mmflow.mmode.normal import unpack_upper
from mmflow.workflow.engine.context import _telescope
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import small_config


@pytest.mark.parametrize("groups", [1, 3])
def test_workflow_normal_equations_and_alm_equal_the_engine(tmp_path, groups):
    """One group: bit for bit. Three: each group's partial holds only its baselines' m-modes, and
    the partials summed in complex128 then rounded once differ from the engine's streaming
    complex64 sum by rounding only."""
    run = tmp_path / "run"
    cfg = small_config(run, "transfer.dtype=float32", f"transfer.groups={groups}", "imaging.lcurve=false",
                       "mmode.splits=[full]", "run.keep=[mmodes.zarr]")
    run_workflow(cfg, only=["simulate", "mmodes", "transfer", "normal", "solve"], progress=False,
                 log=lambda *a: None)
    mg = zarr.open_group(str(run / "mmodes.zarr"), mode="r")
    ng = zarr.open_group(str(run / "normal.zarr"), mode="r")
    ag = zarr.open_group(str(run / "alm.zarr"), mode="r")
    tel = _telescope(cfg.beam.model_dump_json(), str(run))
    lmax = cfg.mmode.lmax
    acc = accumulate_normal_equations(tel, tel.freqs_hz[0], mg["mmodes"][:, 0], lmax,
                                      inv_var=relative_weights(mg["inv_var"][0]),
                                      chunk_size=cfg.transfer.baseline_chunk, dtype=np.float32)
    assert acc.gram[0].dtype == np.complex64 and ng[STORES.normal.gram(0, 0)].dtype == np.complex64
    m_block = cfg.transfer.m_block
    scale = np.abs(acc.gram[0]).max()

    def same(a, b):
        if groups == 1:
            assert np.array_equal(a, b)
        else:
            assert np.abs(a - b).max() <= 2e-6 * max(scale, np.abs(b).max())
    for m in range(lmax + 1):
        m0 = m - m % m_block
        n = lmax - m + 1
        stored = unpack_upper(ng[STORES.normal.gram(0, m0)][m - m0], lmax - m0 + 1)[:n, :n]  # packed, padded
        same(np.triu(stored), np.triu(acc.gram[m]))
        same(ng["rhs"][0, 0, m, m:], acc.rhs[m][0].astype(np.complex128))
    im = cfg.imaging
    alm = solve_alm(acc, im.eps, im.method, dict(zero_monopole=im.zero_monopole, filter_m0=im.filter_m0,
                                                 filter_m1_lmin=im.filter_m1_lmin))
    wf = ag["alm"][0, 0]
    assert np.abs(alm).max() > 0
    for m in range(lmax + 1):
        if groups == 1:
            assert np.array_equal(wf[m, m:], alm[m_slice(lmax, m)]), m
        else:
            assert np.abs(wf[m, m:] - alm[m_slice(lmax, m)]).max() <= 1e-4 * np.abs(alm).max(), m
