"""The full-Stokes fast path (ring FFTs + per-m GEMMs) against independent computations.

* the spin-2 Legendre functions at lmax 1000 against ducc0's spin-2 synthesis of one harmonic;
* the transfer blocks against the reference kernels (ducc0 spin-0 / spin-2 adjoint transforms per
  baseline and correlation), float64 and float32, any correlation order, any Fourier m-block;
* the streamed normal equations (``herk`` per m) against ``B^H W B`` and ``B^H W v`` formed densely
  from the reference blocks.
"""
import ducc0
import numpy as np
import pytest

import mmflow.mmode.polarised_transfer as fast
from mmflow.imaging.polarised import accumulate_polarised_normal
from mmflow.mmode.polarised import CORRELATIONS, make_polarised_grid, reference_transfer_blocks
from mmflow.mmode.spin_legendre import spin2_tables, weighted_spin_tables
from mmflow.mmode.transfer import fringe_bandlimit
from mmflow.telescope.jones import ShortDipoleJones

LAT = np.deg2rad(37.24)
FREQ = 50e6


@pytest.mark.parametrize("l, m", [(1000, 1), (1000, 997), (731, 400), (2, 0), (999, 999), (12, 5)])
def test_spin2_tables_match_ducc0_at_lmax_1000(l, m):
    """``Q + i U_healpy`` of ``E_lm = 1`` is ``-(2_lambda e^{i m phi} + -2_lambda e^{-i m phi})``:
    ``Q(phi = 0) = -2 W`` and ``U_healpy(phi = pi / 2m) = -2 X`` (``-W`` and 0 for m = 0).

    Bound: the ``1 / sin^2 theta`` terms cancel near the poles, so the absolute error grows to
    ~``1e-16 / sin^2 theta`` on the polar rings (2e-11 at lmax 1000 for l = 2); 1e-10 of the peak."""
    lmax = 1000
    nth = lmax + 2
    nphi = 4 * max(m, 1) * int(np.ceil((2 * lmax + 2) / (4 * max(m, 1))))
    alm = np.zeros((2, (lmax + 1) * (lmax + 2) // 2), complex)
    alm[0, m * (2 * lmax + 1 - m) // 2 + l] = 1.0
    q, u = ducc0.sht.experimental.synthesis_2d(alm=alm, spin=2, lmax=lmax, geometry="GL", ntheta=nth, nphi=nphi)
    w, x = spin2_tables(m, lmax, ducc0.misc.GL_thetas(nth))
    w, x = w[l - m], x[l - m]
    scale = np.abs(w).max() + np.abs(x).max()
    assert scale > 0.1  # the functions are O(1) somewhere: the comparison is not of zeros
    if m == 0:
        np.testing.assert_allclose(q[:, 0], -w, atol=1e-10 * scale)
        assert np.abs(x).max() == 0
    else:
        np.testing.assert_allclose(q[:, 0], -2 * w, atol=1e-10 * scale)
        np.testing.assert_allclose(u[:, nphi // (4 * m)], -2 * x, atol=1e-10 * scale)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_flushed_tables_zero_exactly_the_negligible_entries(dtype):
    """``flush=True`` zeroes each row's entries below ``eps^2`` of the row's largest (in ``dtype``) and
    nothing else: compared with the unflushed tables thresholded by numpy. At lmax 1000 near the poles
    float32's tables hold subnormal entries (the reason for the flush): none is left."""
    theta = np.linspace(0.01, np.pi / 2 - 0.001, 300)
    w = np.random.default_rng(3).uniform(0.5, 1.5, theta.size)
    tiny = np.finfo(dtype).eps ** 2
    for m in (0, 400, 900):
        raw = weighted_spin_tables(m, 1000, theta, w, dtype)
        flushed = weighted_spin_tables(m, 1000, theta, w, dtype, flush=True)
        for r, f in zip(raw, flushed):
            small = np.abs(r) < tiny * np.abs(r).max(axis=1, keepdims=True)
            assert np.array_equal(f[~small], r[~small]) and not f[small].any()
            tiniest = np.finfo(dtype).smallest_normal
            if dtype == np.float32 and m == 900:
                assert ((np.abs(r) < tiniest) & (r != 0)).any()  # the raw table has subnormals
            assert not ((np.abs(f) < tiniest) & (f != 0)).any()


@pytest.mark.parametrize("flush", [False, True])
def test_spin_tables_to_a_lower_band_limit_are_the_full_tables_rows(flush):
    """``lmax_spin`` (the transfer's ``imaging.stokes_lmax``) forms ``W``, ``X`` on rows ``l = m..lmax_spin``
    only: each row bit for bit the full table's (every row is formed alone), in the same parity layout over
    its own rows, none above it; ``lambda`` is unchanged."""
    theta = np.linspace(0.01, np.pi / 2 - 0.001, 101)
    w = np.random.default_rng(5).uniform(0.5, 1.5, theta.size)
    lmax = 300
    for m in (0, 1, 3, 120, 200, 201):
        full = weighted_spin_tables(m, lmax, theta, w, np.float32, flush)
        for lmax_spin in (200, m, m + 1):
            lam, w_tab, x_tab = weighted_spin_tables(m, lmax, theta, w, np.float32, flush, lmax_spin=lmax_spin)
            n_s = max(0, lmax_spin - m + 1)
            assert np.array_equal(lam, full[0]) and w_tab.shape == x_tab.shape == (n_s, theta.size)
            i = np.arange(n_s)
            rows = np.where(i % 2 == 0, i // 2, (n_s + 1) // 2 + i // 2)  # l = m + i in its own layout
            rows_full = np.where(i % 2 == 0, i // 2, (lmax - m) // 2 + 1 + i // 2)
            assert np.array_equal(w_tab[rows], full[1][rows_full]) and np.array_equal(x_tab[rows], full[2][rows_full])


def _setup(nb, lmax, seed=0):
    jones = ShortDipoleJones(horizon_taper=3.0)
    rng = np.random.default_rng(seed)
    b = rng.normal(size=(nb, 3)) * 3.0
    b[:, 2] *= 0.3
    grid = make_polarised_grid(LAT, jones, FREQ, lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), jones.lmax_hint))
    return grid, b


@pytest.mark.parametrize("correlations", [CORRELATIONS, ("xy", "yx", "xx")])
def test_fast_blocks_equal_the_reference_kernels(correlations, monkeypatch):
    grid, b = _setup(5, 40)
    ref = reference_transfer_blocks(grid, b, correlations)
    peak = max(np.abs(r).max() for r in ref)
    got = fast.polarised_transfer_blocks(grid, b, correlations)
    assert [g.shape for g in got] == [r.shape for r in ref]
    for m, (g, r) in enumerate(zip(got, ref)):
        assert np.abs(g - r).max() < 1e-12 * peak, m
    # float32: the same to single precision
    got32 = fast.polarised_transfer_blocks(grid, b, correlations, dtype=np.float32)
    assert got32[3].dtype == np.complex64
    assert max(np.abs(g - r).max() for g, r in zip(got32, ref)) < 2e-5 * peak
    # Fourier arrays in m-blocks of any size: the same bits
    monkeypatch.setattr(fast, "FOURIER_BUDGET_BYTES", 1)
    for g, h in zip(got, fast.polarised_transfer_blocks(grid, b, correlations)):
        np.testing.assert_array_equal(g, h)


def test_a_ring_transforms_only_its_distinct_kernels(monkeypatch):
    """Through the short dipole's real Jones vectors V is zero in xx and yy and yx's I, Q, U, V kernels are
    xy's with signs +, +, +, -: a ring transforms 10 of its 16 kernels, the copies are the transformed ones'
    (negated for V) bit for bit, and the Fourier arrays equal those of every kernel transformed to rounding."""
    grid, b = _setup(5, 30)
    k = fast.active_rings(grid)[3]

    def kernels(ring):
        return fast.ring_kernels(grid, ring, CORRELATIONS).reshape(grid.n_phi, -1).T

    k_n, k_s = kernels(k), kernels(len(grid.theta) - 1 - k)
    distinct, copies, zero = fast.distinct_kernels(k_n, k_s)
    f = {x + corr: 4 * a + c for a, x in enumerate(fast.FIELDS) for c, corr in enumerate(CORRELATIONS)}
    assert len(distinct) == 10 and sorted(zero) == [f["Vxx"], f["Vyy"]]
    assert copies == {f["Ixy"]: [(f["Iyx"], 1)], f["Vxy"]: [(f["Vyx"], -1)], f["Qxy"]: [(f["Qyx"], 1)],
                      f["Uxy"]: [(f["Uyx"], 1)]}
    fsum, fdiff, _ = fast.polarised_fourier(grid, b, (0, 12), CORRELATIONS, np.complex128)
    # (m, pair, ring, field, corr, cols): field (I, V, Q, U) = (pair, field) (0, 0), (0, 1), (1, 0), (1, 1)
    for arr in (fsum, fdiff):
        np.testing.assert_array_equal(arr[:, 0, :, 0, 3], arr[:, 0, :, 0, 2])  # I of yx is I of xy
        np.testing.assert_array_equal(arr[:, 0, :, 1, 3], -arr[:, 0, :, 1, 2])  # V of yx is -V of xy
        assert not arr[:, 0, :, 1, :2].any()  # V of xx and yy
    monkeypatch.setattr(fast, "distinct_kernels", lambda k_n, k_s: (list(range(len(k_n))), {}, []))
    every = fast.polarised_fourier(grid, b, (0, 12), CORRELATIONS, np.complex128)
    for got, ref in zip((fsum, fdiff), every[:2]):
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13 * np.abs(ref).max())


def test_passes_sharing_their_fourier_buffers_give_the_same_bits(monkeypatch):
    """Passes of several baseline sets and grids through one :class:`FourierBuffers` (blocks of m one at a
    time, E, B, V to a lower band limit: polarised and I-only arrays of several shapes in the same memory,
    dirtied by every earlier pass) give the blocks of passes on fresh arrays, bit for bit."""
    monkeypatch.setattr(fast, "FOURIER_BUDGET_BYTES", 200_000)  # several blocks a pass

    def blocks(grid, b, buffers):
        out = {}
        fast.polarised_pass(grid, b, lambda m, blk: out.__setitem__(m, blk.copy()), dtype=np.float32, lmax_pol=12,
                            buffers=buffers)
        return out

    shared = fast.FourierBuffers()
    for nb, lmax, seed in ((6, 30, 1), (3, 24, 2), (7, 36, 3), (4, 30, 4)):
        grid, b = _setup(nb, lmax, seed)
        fresh, reused = blocks(grid, b, None), blocks(grid, b, shared)
        assert fresh.keys() == reused.keys() and len(fresh) == lmax + 1
        for m in fresh:
            np.testing.assert_array_equal(fresh[m], reused[m])
    assert shared.flat[0].size > 0


@pytest.mark.parametrize("per_baseline, lmax_p, m_range",
                         [(False, None, None), (True, None, None), (True, 10, (5, 14))])
def test_streamed_normal_equations_equal_the_dense_products(per_baseline, lmax_p, m_range):
    """With per-baseline lmax the dense products use the reference blocks with each baseline's
    coefficients above its lmax_b zeroed, and its m-modes only up to its chunk's largest lmax_b.
    With a band limit of its own for E, B, V (``lmax_p``) the dense products keep T's columns to lmax
    and E's, B's, V's to ``lmax_p``; a block of m (``m_range``, its m-modes only) holds those m alone."""
    grid, b = _setup(7, 24, seed=3)
    rng = np.random.default_rng(4)
    lmax, nc = grid.lmax, 4
    mm = rng.normal(size=(2, lmax + 3, 2, nc, len(b))) + 1j * rng.normal(size=(2, lmax + 3, 2, nc, len(b)))
    w = rng.uniform(0.5, 2.0, (nc, len(b)))
    lmax_b = np.array([24, 9, 17, 5, 24, 12, 20]) if per_baseline else None
    m0, m1 = m_range or (0, lmax + 1)
    given = mm if m_range is None else mm[:, m0:m1]
    normal = accumulate_polarised_normal(grid, b, given, w, chunk_size=3, lmax_b=lmax_b, lmax_p=lmax_p,
                                         m_range=m_range)
    assert list(normal.m_range) == list(range(m0, m1))
    blocks = reference_transfer_blocks(grid, b)
    if per_baseline:
        # chunks of three by lmax_b: (5, 9, 12) -> 12, (17, 20, 24) -> 24, (24) -> 24
        top = np.array([24, 12, 24, 12, 24, 12, 24])
        for m, blk in enumerate(blocks):
            ell = np.arange(m, lmax + 1)
            blk *= (ell[None, :] <= lmax_b[:, None])[None, None, :, :] if m == 0 else \
                np.tile(ell[None, :] <= lmax_b[:, None], (2, 1))[None, None]
            live = top >= m  # a chunk's m-modes enter only its m <= lmax_c
            mm[:, m, :, :, ~live] = 0
    for m in [m for m in (0, 1, 5, 9, 13, lmax) if m0 <= m < m1]:
        blk = blocks[m]  # (corr, 4, rows, L)
        n_l = blk.shape[3]
        n_p = n_l if lmax_p is None else max(0, lmax_p - m + 1)
        cols = np.concatenate([np.arange(n_l)] + [x * n_l + np.arange(n_p) for x in (1, 2, 3)])
        a = blk.transpose(0, 2, 1, 3).reshape(nc * blk.shape[2], -1)[:, cols]  # rows (corr, +-m, b), cols (X, l)
        wr = np.tile(w, (1, 1 if m == 0 else 2)).reshape(-1)
        v = (mm[:, m, :1] if m == 0 else mm[:, m]).transpose(0, 2, 1, 3).reshape(2, -1)
        g = a.conj().T @ (wr[:, None] * a)
        scale = np.abs(g).max()
        assert normal.gram[m - m0].shape == (n_l + 3 * n_p,) * 2 and normal.sizes(m) == (n_l, n_p)
        assert np.abs(normal.gram[m - m0] - g).max() < 1e-12 * scale
        np.testing.assert_allclose(normal.rhs[m - m0], (v * wr) @ a.conj(),
                                   atol=1e-12 * np.abs(normal.rhs[m - m0]).max())
        np.testing.assert_allclose(normal.vhv[:, m], np.sum(wr * np.abs(v) ** 2, axis=1), rtol=1e-12)
