"""End-to-end noiseless imaging, Tikhonov limits, alternatives, L-curves and filters."""
import numpy as np
import pytest

from mmflow.analysis.peaks import measure_peak
from mmflow.conventions import m_slice, radec_to_vec
from mmflow.imaging import lcurve, solvers
from mmflow.imaging.filters import apply_filters, filter_mask
from mmflow.imaging.solvers import solve_alm
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.mmode.transform import mmode_transform, sidereal_bins
from mmflow.simulate.visibilities import SkyPoints, gauss_legendre_points, simulate_drift_scan
from mmflow.sky.diffuse import alm_to_map, band_limited_random_alm
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.beams import SinElevationBeam

NO_FILTER = dict(filter_m0=False, filter_m1_lmin=None, zero_monopole=False)


@pytest.fixture(scope="module")
def core26():
    return Telescope(ovro_lwa_layout("core", radius_m=25), SinElevationBeam(1.5), [40e6])


def _mmodes(tel, sky, lmax, f=40e6):
    n = 2 * lmax + 4
    lst = 2 * np.pi * np.arange(n) / n
    return mmode_transform(sidereal_bins(lst, simulate_drift_scan(tel, f, lst, sky), n_bins=n)[0], lmax)


def test_point_sources_imaged_within_a_tenth_of_the_psf(core26):
    lmax = 64
    ra, dec = np.deg2rad([30, 120, 200, 290, 250]), np.deg2rad([60, 20, 45, 5, 75])
    vecs = radec_to_vec(ra, dec)
    mm = _mmodes(core26, SkyPoints(vecs, np.array([100.0, 80, 120, 60, 90])), lmax)
    acc = accumulate_normal_equations(core26, 40e6, mm, lmax, per_baseline_lmax=False)
    hmap = alm_to_map(solve_alm(acc, 1e-3, filters=NO_FILTER), 128, lmax)
    for v in vecs:
        pk = measure_peak(hmap, v, np.deg2rad(8))
        assert 2.0 < np.rad2deg(pk["fwhm_rad"]) < 12.0
        assert pk["offset_rad"] < 0.1 * pk["fwhm_rad"]


def test_diffuse_sky_in_measured_modes_recovered_to_one_percent(core26):
    lmax = 30
    truth = band_limited_random_alm(lmax, seed=3)
    sky = gauss_legendre_points(truth, lmax, 2 * lmax + 120)
    acc = accumulate_normal_equations(core26, 40e6, _mmodes(core26, sky, lmax), lmax)
    eps = 1e-6
    got = solve_alm(acc, eps, filters=NO_FILTER)
    err = nrm = 0.0
    for m in range(lmax + 1):
        s, v = np.linalg.eigh(acc.full_gram(m))
        meas = v[:, s > 1e4 * eps]  # "measured" modes: singular values >> sqrt(eps)
        t, g = truth[m_slice(lmax, m)], got[m_slice(lmax, m)]
        pt, pg = meas @ (meas.conj().T @ t), meas @ (meas.conj().T @ g)
        err += np.sum(np.abs(pg - pt) ** 2)
        nrm += np.sum(np.abs(pt) ** 2)
    assert nrm > 0.5 * np.sum(np.abs(truth) ** 2)  # most of the sky is measured
    assert np.sqrt(err / nrm) < 0.01


def test_tikhonov_to_zero_eps_recovers_full_rank_toy_exactly(rng):
    b = rng.normal(size=(40, 12)) + 1j * rng.normal(size=(40, 12))
    a = rng.normal(size=12) + 1j * rng.normal(size=12)
    g, r = b.conj().T @ b, b.conj().T @ (b @ a)
    for eps in (1e-6, 1e-9, 1e-12):
        np.testing.assert_allclose(solvers.tikhonov(g, r, eps)[0], a, atol=1e-4 * eps ** 0.5 + 1e-9)
    np.testing.assert_allclose(solvers.moore_penrose(g, r, 1e-8), a, atol=1e-9)
    np.testing.assert_allclose(solvers.with_prior(g, r, 1e-12, a), a, atol=1e-12)


def test_tikhonov_matches_svd_formula_and_alternatives_behave(rng):
    b = rng.normal(size=(30, 10)) + 1j * rng.normal(size=(30, 10))
    b[:, -1] = 1e-4 * b[:, 0]  # a nearly unmeasured direction
    v = rng.normal(size=30) + 1j * rng.normal(size=30)
    g, r = b.conj().T @ b, b.conj().T @ v
    eps = 0.5
    uu, s, vh = np.linalg.svd(b, full_matrices=False)
    ref = vh.conj().T @ (s / (s**2 + eps) * (uu.conj().T @ v))
    np.testing.assert_allclose(solvers.tikhonov(g, r, eps)[0], ref, atol=1e-12)
    mp = solvers.moore_penrose(g, r, 1e-2)
    keep = s > 1e-2
    ref_mp = vh[keep].conj().T @ ((uu[:, keep].conj().T @ v) / s[keep])
    np.testing.assert_allclose(mp, ref_mp, atol=1e-10)
    # smoothness prior on l(l+1): the solution minimises ||v - Ba||^2 + eps sum l(l+1)|a|^2
    ell = np.arange(10)
    a_s = solvers.generalized(g, r, eps, solvers.smoothness_weights(ell))
    d = np.maximum(ell * (ell + 1.0), 1e-12 * 90)
    np.testing.assert_allclose((g + eps * np.diag(d)) @ a_s, r, atol=1e-10)
    assert 0 < solvers.singular_fraction_above(g, eps) < 1


def test_lcurve_from_normal_equations_matches_explicit_solves(rng):
    b = rng.normal(size=(50, 15)) + 1j * rng.normal(size=(50, 15))
    v = rng.normal(size=50) + 1j * rng.normal(size=50)
    g, r, vhv = b.conj().T @ b, b.conj().T @ v, float(np.vdot(v, v).real)
    eps = lcurve.default_eps_grid()
    assert len(eps) == 200
    sol, res = lcurve.lcurve_block(g, r, vhv, eps)
    for k in (0, 77, 199):
        a = solvers.tikhonov(g, r, eps[k])[0]
        assert sol[k] == pytest.approx(np.sum(np.abs(a) ** 2), rel=1e-8)
        assert res[k] == pytest.approx(np.sum(np.abs(v - b @ a) ** 2), rel=1e-8)
    assert np.all(np.diff(sol) <= 1e-12) and np.all(np.diff(res) >= -1e-9)
    assert eps[0] < lcurve.lcurve_corner(sol, res, eps) < eps[-1]


def test_m_filters_follow_the_paper():
    lmax = 150
    assert not filter_mask(0, lmax).any()
    keep1 = filter_mask(1, lmax)
    assert keep1[np.arange(1, lmax + 1) <= 100].all() and not keep1[np.arange(1, lmax + 1) > 100].any()
    assert filter_mask(2, lmax).all()
    only_monopole = filter_mask(0, lmax, filter_m0=False)
    assert not only_monopole[0] and only_monopole[1:].all()
    alm = np.ones((lmax + 1) * (lmax + 2) // 2, complex)
    out = apply_filters(alm, lmax)
    assert np.all(out[m_slice(lmax, 0)] == 0) and np.all(out[m_slice(lmax, 2)] == 1)
