"""The fused channel engine (issue 12): adaptive chunks, in-place herk, inertia count, bench JSON."""
import json

import numpy as np
import pytest

from mmflow.imaging.solvers import count_eigenvalues_above, singular_fraction_above
from mmflow.mmode.engine import (CHUNK_LMAX_SPAN, GridCache, accumulate_normal_equations,
                                 chunk_blocks, plan_chunks)
from mmflow.mmode.legendre import legendre_table, weighted_legendre_table
from mmflow.mmode.normal import herk_into

FREQ = 40e6


def test_herk_into_updates_only_the_leading_upper_block(rng):
    for dtype in (np.complex64, np.complex128):
        g = np.zeros((9, 9), dtype, order="F")
        g[:] = 5.0  # untouched entries must keep their value
        x = (rng.normal(size=(7, 4)) + 1j * rng.normal(size=(7, 4))).astype(dtype)  # (l, baseline), lda 4
        herk_into(g, x, 3, 6, 4)  # A = x[:6, :3]^T: 3 baselines, 6 columns
        a = x[:6, :3].T
        want = 5.0 + a.conj().T @ a
        tol = 1e-5 if dtype == np.complex64 else 1e-12
        iu = np.triu_indices(6)
        np.testing.assert_allclose(g[:6, :6][iu], want[iu], rtol=tol, atol=tol)
        assert np.all(g[6:, :] == 5.0) and np.all(g[:, 6:] == 5.0) and np.all(g[:6, :6][np.tril_indices(6, -1)] == 5.0)


def test_fused_normal_equations_equal_the_sum_over_transfer_blocks(small_telescope, rng):
    """G_m = sum_b B^H W B and r_m = B^H W v from the fused step equal a direct numpy sum."""
    tel, lmax = small_telescope, 40
    n = len(tel.antenna_pairs())
    mm = rng.normal(size=(2, lmax + 1, 2, n)) + 1j * rng.normal(size=(2, lmax + 1, 2, n))
    w = rng.uniform(0.5, 2.0, n)
    acc = accumulate_normal_equations(tel, FREQ, mm, lmax, inv_var=w, chunk_size=8, dtype=np.float64)
    chunks, lmax_b = plan_chunks(tel, FREQ, lmax, 8)
    assert len(chunks) > 1 and lmax_b.min() < lmax  # several chunks, per-baseline truncation exercised
    g = {m: 0 for m in range(lmax + 1)}
    r = {m: 0 for m in range(lmax + 1)}
    vhv = np.zeros((2, lmax + 1))
    cache = GridCache(tel, FREQ)
    for c in chunks:
        for m, blk in chunk_blocks(tel, FREQ, c, lmax, lmax_b, np.float64, cache):
            ww = w[c.index] if m == 0 else np.concatenate([w[c.index], w[c.index]])
            v = mm[:, m, 0][:, c.index] if m == 0 else np.concatenate([mm[:, m, 0][:, c.index],
                                                                        mm[:, m, 1][:, c.index]], axis=1)
            g[m] = g[m] + blk.conj().T @ (ww[:, None] * blk)
            r[m] = r[m] + (blk.conj().T @ (ww[None, :] * v).T).T
            vhv[:, m] += (ww * np.abs(v) ** 2).sum(axis=1)
    for m in (0, 1, 7, lmax):
        np.testing.assert_allclose(acc.full_gram(m), g[m], rtol=1e-10, atol=1e-10 * np.abs(g[0]).max())
        np.testing.assert_allclose(acc.rhs[m], r[m], rtol=1e-10, atol=1e-10 * np.abs(r[0]).max())
    np.testing.assert_allclose(acc.vhv, vhv, rtol=1e-12)


def test_fused_normal_equations_give_the_same_bits_for_any_thread_budget(small_telescope, rng, monkeypatch):
    tel, lmax = small_telescope, 30
    n = len(tel.antenna_pairs())
    mm = (rng.normal(size=(lmax + 1, 2, n)) + 1j * rng.normal(size=(lmax + 1, 2, n))).astype(np.complex64)
    out = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("MMFLOW_THREADS", threads)
        out.append(accumulate_normal_equations(tel, FREQ, mm, lmax, chunk_size=8, dtype=np.float32))
    for acc in out[1:]:
        for m in range(lmax + 1):
            assert np.array_equal(acc.gram[m], out[0].gram[m]) and np.array_equal(acc.rhs[m], out[0].rhs[m])


def test_adaptive_chunks_of_the_paper_channel():
    """256 stands, 73.152 MHz, lmax 1000: every baseline once, sizes multiples of 64, bounded workspace."""
    from mmflow.telescope import Telescope, ovro_lwa_layout
    from mmflow.telescope.beams import SinElevationBeam

    f = 73.152e6
    tel = Telescope(ovro_lwa_layout("paper-2017"), SinElevationBeam(1.5), [f])
    chunks, lmax_b = plan_chunks(tel, f, 1000, 64)
    idx = np.concatenate([c.index for c in chunks])
    assert len(lmax_b) == 32896 and np.array_equal(np.sort(idx), np.arange(32896))
    sizes = np.array([len(c.index) for c in chunks])
    assert np.all(sizes[:-1] % 64 == 0) and sizes.max() > 64  # short baselines share fatter chunks
    for c in chunks:
        lb = lmax_b[c.index]
        assert c.lmax == lb.max()
        if len(c.index) > 64:
            assert len(c.index) * float(c.lmax) ** 2 <= 64 * 1000**2  # 64 baselines' workspace at lmax 1000
            assert lb.max() <= CHUNK_LMAX_SPAN * lb.min() + 2
    # the cost ~ n lmax_c^3 of the plan is within 3 % of per-baseline cost
    assert (sizes * np.array([c.lmax for c in chunks], float) ** 3).sum() < 1.03 * (lmax_b.astype(float) ** 3).sum()
    # the decomposition depends only on the baselines and settings
    again, _ = plan_chunks(tel, f, 1000, 64)
    assert all(np.array_equal(a.index, b.index) for a, b in zip(chunks, again))


def test_weighted_legendre_table_is_the_weighted_float64_table_rounded_once(rng):
    theta = np.sort(rng.uniform(0.01, np.pi - 0.01, 37))
    w = rng.uniform(0.1, 1.0, 37)
    for m in (0, 3, 40):
        ref = legendre_table(m, 120, theta) * w
        t, colmax = weighted_legendre_table(m, 120, theta, w, np.float32, l_block=32)
        assert t.dtype == np.float32 and np.array_equal(t, ref.astype(np.float32))
        for j in range(colmax.shape[0]):
            np.testing.assert_array_equal(colmax[j], np.abs(ref[32 * j:32 * (j + 1)]).max(axis=0))


@pytest.mark.parametrize("n", [1, 2, 5, 60, 1001])
def test_inertia_count_equals_eigvalsh_count(n, rng):
    """Eigenvalues of G above eps counted from LDL^H of eps I - G, against eigvalsh (n = 1001: lmax 1000)."""
    for trial in range(2 if n < 1001 else 1):
        # a spectrum spread over decades (like a Gram's), with a gap of 1e-3 around eps
        ev = 10 ** rng.uniform(-6, 3, n)
        eps = 10 ** rng.uniform(-4, 1)
        ev[np.abs(np.log10(ev / eps)) < 1e-3] *= 1.01
        q, _ = np.linalg.qr(rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n)))
        g = (q * ev) @ q.conj().T
        g = 0.5 * (g + g.conj().T)
        want = int(np.sum(np.linalg.eigvalsh(g) > eps))
        assert 0 < want < n or n < 5
        assert count_eigenvalues_above(g, eps) == want
        assert singular_fraction_above(g, eps) == want / n


def test_inertia_count_handles_indefinite_two_by_two_pivots():
    g = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 3.0]], complex)  # eigenvalues -1, 1, 3
    assert count_eigenvalues_above(g, 0.5) == 2 and count_eigenvalues_above(g, 2.0) == 1
    assert count_eigenvalues_above(g, -2.0) == 3 and count_eigenvalues_above(g, 5.0) == 0


def test_bench_channel_prints_every_phase_and_the_projection(capsys, monkeypatch):
    from mmflow.cli import main

    monkeypatch.setenv("MMFLOW_THREADS", "1")
    assert main(["bench", "channel", "--lmax", "48", "--scale", "0.05", "--solve-stride", "8"]) == 0
    res = json.loads(capsys.readouterr().out)
    (case,) = res["cases"]
    assert case["peaks"]["sgemm_gflops_before"] > 0 and case["peaks"]["dgemm_gflops_after"] > 0
    assert len(case["calibration"]) == 2 and case["legendre_fraction_of_gemm_peak"] > 0
    assert case["baselines_total"] == 32896 and 0 < case["baselines_run"] < 32896
    phases = case["measured"]["phases_s"]
    for key in ("grid_s", "tables_s", "fourier_s", "legendre_s", "herk_s", "rhs_scale_s"):
        assert phases[key] >= 0 and key in case["model_for_run"]
    assert abs(sum(phases.values()) - case["measured"]["wall_s"]) < 1e-6
    assert case["measured"]["solve"]["m_solved"] == 7 and case["measured"]["peak_rss_mb"] > 0
    proj = case["projection_full_channel"]
    assert "PROJECTION" in proj["label"] and proj["total_minutes"] > 0
    chans = case["projection_paper_channels"]
    tg = [chans[f]["transfer_and_gram_s"] for f in ("36.528", "52.224", "73.152")]
    assert tg[0] < tg[1] < tg[2]  # longer baselines in wavelengths at higher frequencies cost more
