"""Full Stokes in blocks of m and with Q, U, V to a band limit of their own (``imaging.stokes_lmax``).

* the normal equations accumulated and solved per block of m give the bits of one pass over every m;
  the observer that factorises each m again per call (the stokes stage's second phase) gives the same
  bits as the one that keeps its factors (all, or some: the second phase at the paper's scale), and so does
  the block task's solve and leakage with each m factorised once (``solution_and_leakage``); each chunk of
  baselines on a grid of its own size gives the same normal equations to the quadrature's rounding (1e-8;
  measured ~4e-10);
* with ``lmax_p < lmax`` the solve is the reduced problem: the dense least squares over T's harmonics to
  lmax and E's, B's, V's to ``lmax_p``, from the reference kernels' transfer blocks, solved by numpy.
"""
import numpy as np

from mmflow.conventions import m_slice, n_alm, stokes_sizes
from mmflow.imaging.polarised import (PolarisedObserver, _greedy_blocks, accumulate_polarised_normal, penalty,
                                      solve_polarised, stokes_m_blocks)
from mmflow.imaging.solvers import floored_penalty
from mmflow.mmode.polarised import make_polarised_grid, reference_transfer_blocks
from mmflow.mmode.transfer import fringe_bandlimit
from mmflow.telescope.jones import ShortDipoleJones

LAT = np.deg2rad(37.24)
FREQ = 50e6
LMAX = 20


def _scene(nb=9, seed=5):
    jones = ShortDipoleJones(horizon_taper=3.0)
    rng = np.random.default_rng(seed)
    b = rng.normal(size=(nb, 3)) * np.linspace(0.3, 2.5, nb)[:, None]  # short and long baselines
    b[:, 2] *= 0.3
    mm = rng.normal(size=(2, LMAX + 1, 2, 4, nb)) + 1j * rng.normal(size=(2, LMAX + 1, 2, 4, nb))
    w = rng.uniform(0.5, 2.0, (4, nb))
    return jones, b, mm, w


def _grid(jones, b, lmax):
    return make_polarised_grid(LAT, jones, FREQ, lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), jones.lmax_hint))


def test_blocks_of_m_solve_as_one_pass_and_chunk_grids_give_the_same_normal_equations():
    jones, b, mm, w = _scene()
    lmax_b = np.minimum(LMAX, np.ceil(1.1 * 2 * np.pi * np.linalg.norm(b, axis=1)).astype(int) + 4)
    assert lmax_b.min() < LMAX // 2  # some chunks stop far below lmax: their grids are smaller
    grid = _grid(jones, b, LMAX)
    one = accumulate_polarised_normal(grid, b, mm, w, chunk_size=3, lmax_b=lmax_b, lmax_p=12)
    scale = max(np.abs(np.diag(g)).max() for g in one.gram)
    eps, filters = (1e-3 * scale, 1e-2 * scale), {"filter_m0": False, "zero_monopole": True, "filter_m1_lmin": 15}
    x_one = solve_polarised(one, eps, filters)
    leak_in = np.zeros_like(x_one[0])
    leak_in[0] = x_one[0, 0]
    leak_one = PolarisedObserver(one, eps, filters)(leak_in)
    blocks = stokes_m_blocks(LMAX, 12, budget_bytes=32 * 60 ** 2)  # block m = 0 alone, later ones wider
    assert len(blocks) >= 4 and blocks[0] == (0, 1) and blocks[-1][1] == LMAX + 1
    x_blk, leak_blk = np.zeros_like(x_one), np.zeros_like(leak_one)
    tops = []

    def grid_of(top, index):  # each chunk's grid exact to its own top and fringes
        tops.append(top)
        return _grid(jones, b[index], top)

    for m0, m1 in blocks:
        part = accumulate_polarised_normal(grid, b, mm[:, m0:m1], w, chunk_size=3, lmax_b=lmax_b, lmax_p=12,
                                           m_range=(m0, m1))
        kept = PolarisedObserver(part, eps, filters)
        again = PolarisedObserver(part, eps, filters, keep_factors=False)
        sl = slice(m_slice(LMAX, m0).start, m_slice(LMAX, m1 - 1).stop)
        x = kept.solution()
        np.testing.assert_array_equal(x, again.solution())  # factorised again per call: the same bits
        some = PolarisedObserver(part, eps, filters, keep_factors=[m0, m1 - 1])  # some factors kept, the rest made
        assert set(some.blocks) == {m0, m1 - 1}
        np.testing.assert_array_equal(some(leak_in), kept(leak_in))
        assert np.abs(np.delete(x, np.r_[sl], axis=-1)).max() == 0  # nothing outside the block
        x_blk[..., sl] = x[..., sl]
        leak_blk[..., sl] = kept(leak_in)[..., sl]
        # the block task's one pass (each m factorised once, none kept): the solve's and the leakage's bits
        x_once, leak_once = again.solution_and_leakage()
        np.testing.assert_array_equal(x_once, x)
        np.testing.assert_array_equal(leak_once[..., sl], leak_blk[0, ..., sl])
        # the chunks on grids of their own size: the same normal equations to the quadrature's rounding
        small = accumulate_polarised_normal(grid_of, b, mm[:, m0:m1], w, chunk_size=3, lmax_b=lmax_b, lmax_p=12,
                                            m_range=(m0, m1), lmax=LMAX)
        for g, h in zip(small.gram, part.gram):
            assert np.abs(g - h).max() < 1e-8 * np.abs(h).max()
        np.testing.assert_allclose(np.concatenate(small.rhs, axis=1), np.concatenate(part.rhs, axis=1),
                                   atol=1e-8 * max(np.abs(r).max() for r in part.rhs))
    assert min(tops) < LMAX  # short baselines' chunks ran on smaller grids
    np.testing.assert_array_equal(x_blk, x_one)  # per block: the same bits as one pass
    np.testing.assert_array_equal(leak_blk, leak_one)


def test_blocks_of_m_are_as_few_as_the_budget_allows_and_balanced():
    """At the paper's scale (lmax 1000, Q, U, V to 256, complex64 Grams, 3 splits x 32,896 baselines' m-modes,
    4 GiB) the greedy fill from m = 0 leaves a last block of a few m, which would pay the ring stage of every
    long baseline for them: the blocks are as many as the greedy fill's, each within the budget, and balanced
    (the largest no larger than the greedy fill's, the smallest more than half of it)."""
    lmax, lmax_p, budget, per_m = 1000, 256, 4 * 2 ** 30, 3 * 2 * 4 * 32896 * 16
    cost = [8.0 * float(sum(stokes_sizes(m, lmax, lmax_p) * np.array([1, 3]))) ** 2 + per_m for m in range(lmax + 1)]
    greedy = _greedy_blocks(cost, budget)
    blocks = stokes_m_blocks(lmax, lmax_p, budget, per_m, bytes_per_element=8)
    assert greedy[-1][1] - greedy[-1][0] < 10  # the runt
    assert len(blocks) == len(greedy) and blocks[0][0] == 0 and blocks[-1][1] == lmax + 1
    assert all(a[1] == b[0] for a, b in zip(blocks, blocks[1:]))  # contiguous
    used = [sum(cost[m0:m1]) for m0, m1 in blocks]
    assert max(used) <= budget and max(used) <= max(sum(cost[m0:m1]) for m0, m1 in greedy)
    assert min(used) > 0.5 * max(used)


def test_a_lower_band_limit_for_q_u_v_solves_the_reduced_dense_problem():
    jones, b, mm, w = _scene(nb=6, seed=8)
    lmax, lmax_p = 14, 6
    grid = _grid(jones, b, lmax)
    normal = accumulate_polarised_normal(grid, b, mm[:, :lmax + 1], w, lmax_p=lmax_p)
    blocks = reference_transfer_blocks(grid, b)  # ducc0 transforms per baseline: the independent kernels
    scale = max(np.abs(np.diag(g)).max() for g in normal.gram)
    eps = (1e-4 * scale, 1e-3 * scale)
    x = solve_polarised(normal, eps)
    assert x.shape == (2, 4, n_alm(lmax))
    for m in range(lmax + 1):
        blk = blocks[m]  # (corr, 4, rows, L)
        n_l = blk.shape[3]
        n_p = max(0, lmax_p - m + 1)
        cols = np.concatenate([np.arange(n_l)] + [s * n_l + np.arange(n_p) for s in (1, 2, 3)])
        a = blk.transpose(0, 2, 1, 3).reshape(4 * blk.shape[2], -1)[:, cols]
        wr = np.tile(w, (1, 1 if m == 0 else 2)).reshape(-1)
        v = (mm[:, m, :1] if m == 0 else mm[:, m]).transpose(0, 2, 1, 3).reshape(2, -1)
        g = a.conj().T @ (wr[:, None] * a) + np.diag(floored_penalty(penalty(eps, n_l, n_p)))
        dense = np.linalg.solve(g, ((v * wr) @ a.conj()).T).T  # (split, n_l + 3 n_p)
        sl = m_slice(lmax, m)
        got = np.concatenate([x[:, 0, sl]] + [x[:, s, sl][:, :n_p] for s in (1, 2, 3)], axis=1)
        np.testing.assert_allclose(got, dense, atol=1e-9 * np.abs(dense).max())
        assert np.abs(x[:, 1:, sl][..., n_p:]).max(initial=0.0) == 0  # no Q, U, V above lmax_p
