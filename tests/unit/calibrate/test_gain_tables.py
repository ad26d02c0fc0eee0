"""Interval solutions smoothed in time (``mmflow.calibrate.gain_tables.smooth_gains_at``).

Known answers: a drift linear in log-amplitude and phase is returned exactly by the local linear fit
whatever phase reference each interval's solution has; an interval of weight 0 (the model left too
much of its data unexplained) does not move the result; beyond the last used interval the gains
there hold; an antenna with no weight anywhere is flagged.
"""
import numpy as np

from mmflow.calibrate.gain_tables import smooth_gains_at

N_ANT, N_POL, K, STEP = 6, 2, 12, 8


def _drift(t, rng_seed=0):
    """``g(t) = g0 exp((a + i p) t)``: linear in log-amplitude and phase (t in integrations)."""
    rng = np.random.default_rng(rng_seed)
    g0 = rng.uniform(0.7, 1.3, (N_ANT, N_POL)) * np.exp(1j * rng.uniform(-np.pi, np.pi, (N_ANT, N_POL)))
    a, p = rng.uniform(-2e-4, 2e-4, (2, N_ANT, N_POL))
    return g0[None] * np.exp(np.multiply.outer(np.asarray(t, float), a + 1j * p))


def _intervals():
    solve = np.array([(k * STEP, (k + 1) * STEP) for k in range(K)])
    centre = (solve[:, 0] + solve[:, 1] - 1) / 2
    rng = np.random.default_rng(3)
    ref = np.exp(1j * rng.uniform(-np.pi, np.pi, (K, 1, N_POL)))  # each interval's own phase reference
    return solve, _drift(centre) * ref


def _same_up_to_phase(g, truth):
    r = g / truth
    return np.abs(r / np.mean(r, axis=1, keepdims=True) - 1).max()


def test_a_linear_drift_is_followed_exactly():
    solve, gains = _intervals()
    rows = np.arange(K * STEP)
    w = np.random.default_rng(4).uniform(0.5, 2.0, K)
    g, fl = smooth_gains_at(rows, gains, np.zeros(gains.shape, bool), solve, w, scale=10.0)
    assert not fl.any()
    inside = (rows >= (STEP - 1) / 2) & (rows <= K * STEP - (STEP + 1) / 2)
    assert _same_up_to_phase(g[inside], _drift(rows[inside])) < 1e-9
    g2, _ = smooth_gains_at(rows, gains, np.zeros(gains.shape, bool), solve, w, scale=10.0, degree=2)
    assert _same_up_to_phase(g2[inside], _drift(rows[inside])) < 1e-9
    # a weighted mean (degree 0) is biased on the same drift
    g0, _ = smooth_gains_at(rows, gains, np.zeros(gains.shape, bool), solve, w, scale=10.0, degree=0)
    assert _same_up_to_phase(g0[inside], _drift(rows[inside])) > 1e-3


def test_untrusted_intervals_and_flags_do_not_move_it():
    solve, gains = _intervals()
    rows = np.arange(K * STEP)
    flags = np.zeros(gains.shape, bool)
    w = np.ones(K)
    ref, _ = smooth_gains_at(rows, gains, flags, solve, w, scale=10.0)
    bad = gains.copy()
    bad[3] *= 5 * np.exp(2j)  # a solution gone wrong, given weight 0
    bad[7, 2] = 0
    flags[7, 2] = True  # one antenna flagged in one interval: its other intervals carry it
    w[3] = 0
    g, fl = smooth_gains_at(rows, bad, flags, solve, w, scale=10.0)
    assert not fl.any()
    assert _same_up_to_phase(g, _drift(rows)) < 0.01
    assert _same_up_to_phase(g, ref) < 0.01
    # beyond the last used centre (the last intervals untrusted) the fit there holds
    w[-3:] = 0
    g, _ = smooth_gains_at(rows, gains, np.zeros(gains.shape, bool), solve, w, scale=10.0)
    last = (K - 4) * STEP + (STEP - 1) / 2
    late = rows >= last
    assert _same_up_to_phase(g[late], np.broadcast_to(g[late][:1], g[late].shape)) < 1e-12


def test_an_antenna_without_weight_is_flagged():
    solve, gains = _intervals()
    flags = np.zeros(gains.shape, bool)
    flags[:, 1, 0] = True
    g, fl = smooth_gains_at(np.arange(K * STEP), np.where(flags, 0, gains), flags, solve, np.ones(K), scale=10.0)
    assert fl[:, 1, 0].all() and not fl[:, 1, 1].any() and not np.delete(fl, 1, axis=1).any()
    assert (g[:, 1, 0] == 0).all()
