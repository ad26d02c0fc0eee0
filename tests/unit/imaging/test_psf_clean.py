"""PSF of Tikhonov m-mode maps and m-mode CLEAN (paper section 2.4)."""
import healpy
import numpy as np
import pytest
from scipy.special import eval_legendre

from mmflow.conventions import m_slice, radec_to_vec
from mmflow.imaging import psf
from mmflow.imaging.filters import filter_mask
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.sky.frames import tangent_basis
from mmflow.sky.harmonics import point_sources_alm, synthesize_at
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.beams import SinElevationBeam

LMAX = 64


@pytest.fixture(scope="module")
def core_acc():
    """Normal equations of 26 OVRO-LWA core stands (r < 25 m) at 40 MHz, lmax 64 (data unused)."""
    tel = Telescope(ovro_lwa_layout("core", radius_m=25), SinElevationBeam(1.5), [40e6])
    mm = np.zeros((LMAX + 1, 2, len(tel.antenna_pairs())), complex)
    return tel, accumulate_normal_equations(tel, 40e6, mm, LMAX)


def test_cholesky_path_equals_direct_solve(core_acc, rng):
    _, acc = core_acc
    eps = 1e-2 * max(np.abs(acc.full_gram(m)).max() for m in (1, 5))
    for m in (0, 1, 5, 40):
        g = acc.full_gram(m)
        keep = filter_mask(m, LMAX, filter_m1_lmin=30)
        n = LMAX - m + 1
        x = rng.normal(size=(n, 3)) + 1j * rng.normal(size=(n, 3))
        direct = np.zeros_like(x)
        if keep.any():
            gkk = g[np.ix_(keep, keep)]
            direct[keep] = np.linalg.solve(gkk + eps * np.eye(keep.sum()), (g @ x)[keep])
        op = psf.block_operator(m, g, eps, keep)
        np.testing.assert_allclose(psf.observe_block(op, x), direct, atol=1e-10 * np.abs(x).max())
        if op.cho is not None:
            np.testing.assert_allclose(psf.observe(op.cho, g, x, keep), direct, atol=1e-10 * np.abs(x).max())
        assert np.all(direct[~keep] == 0)
        if m == 1:
            assert op.coupling is not None and (~keep).sum() == LMAX - 30


def test_psf_depends_only_on_declination(core_acc):
    _, acc = core_acc
    ops = psf.block_operators(acc, 1e-2)
    dec, ra1, ra2 = np.deg2rad(40.0), 0.3, 2.1
    a1, a2 = psf.psf_alm(ops, LMAX, radec_to_vec(np.array([ra1, ra2]), np.array([dec, dec]))).T
    # the PSF at ra2 is the PSF at ra1 rotated by ra2 - ra1 about the pole
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3))
    pts /= np.linalg.norm(pts, axis=1)[:, None]
    c, s = np.cos(ra2 - ra1), np.sin(ra2 - ra1)
    rot = pts @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])  # rows R_z(dra) p
    f1, f2 = synthesize_at(a1, pts, LMAX), synthesize_at(a2, rot, LMAX)
    np.testing.assert_allclose(f2, f1, atol=1e-10 * np.abs(f1).max())
    # and in harmonic space: a2_lm = a1_lm exp(-i m dra)
    for m in (2, 17):
        np.testing.assert_allclose(a2[m_slice(LMAX, m)], a1[m_slice(LMAX, m)] * np.exp(-1j * m * (ra2 - ra1)),
                                   atol=1e-12 * np.abs(a1).max())


@pytest.mark.parametrize("dec_deg", [-20.0, 45.0, 82.0])
def test_elliptical_fit_of_an_analytic_gaussian_on_the_sphere(dec_deg):
    center = radec_to_vec(1.0, np.deg2rad(dec_deg))
    fmaj, fmin, pa = np.deg2rad(3.0), np.deg2rad(1.8), np.deg2rad(30.0)
    sa, sb = fmaj / psf.FWHM_PER_SIGMA, fmin / psf.FWHM_PER_SIGMA
    e, n = tangent_basis(center)
    ua = np.sin(pa) * e + np.cos(pa) * n  # major axis, PA from north through east
    ub = np.cross(center, ua)

    def gauss(v):  # defined with orthographic (sine) coordinates, not the fit's projection
        return 7.0 * np.exp(-0.5 * ((v @ ua / sa) ** 2 + (v @ ub / sb) ** 2)) * (v @ center > 0)

    fit = psf.measure_beam(gauss, center, np.deg2rad(1.0))
    assert fit["major"] == pytest.approx(fmaj, rel=0.01)
    assert fit["minor"] == pytest.approx(fmin, rel=0.01)
    assert fit["pa"] == pytest.approx(pa, abs=np.deg2rad(1.0))
    assert fit["peak"] == pytest.approx(7.0, rel=0.01)


def test_psf_fwhm_and_peak_at_lmax_800_match_a_legendre_sum():
    """An axisymmetric band-limited PSF, w_l = exp(-l(l+1)/2 L^2): f(g) = sum (2l+1)/(4 pi) w_l P_l(cos g)."""
    lmax, big_l = 800, 300.0
    ell = np.arange(lmax + 1)
    w = np.exp(-ell * (ell + 1) / (2 * big_l**2))
    center = radec_to_vec(0.7, np.deg2rad(45.0))
    alm = healpy.almxfl(point_sources_alm(center[None], [1.0], lmax), w)
    gam = np.linspace(0, np.deg2rad(1.0), 2001)
    prof = ((2 * ell + 1) / (4 * np.pi) * w) @ np.array([eval_legendre(l, np.cos(gam)) for l in ell])
    half = gam[np.argmax(prof < 0.5 * prof[0])]
    fit = psf.measure_psf(alm, lmax, center)
    assert np.isfinite([fit["major"], fit["minor"], fit["value"]]).all()
    assert fit["value"] == pytest.approx(prof[0], rel=1e-9)
    assert fit["major"] == pytest.approx(2 * half, rel=0.01) and fit["minor"] == pytest.approx(2 * half, rel=0.01)


def test_psf_table_peaks_and_widths_vary_smoothly_with_declination(core_acc):
    tel, acc = core_acc
    ops = psf.block_operators(acc, 1e-2)
    decs = np.deg2rad([-30.0, 0.0, 30.0, 60.0, 75.0])
    tab = psf.psf_table(ops, LMAX, decs)
    assert np.all(np.isfinite(tab["major"])) and np.all(tab["major"] >= tab["minor"])
    assert np.all(tab["peak"] > 0)
    # north-south elongation at low elevation: the beam at dec -30 is longer than at the zenith
    zen = np.argmin(np.abs(decs - tel.lat_rad))
    assert tab["major"][0] / tab["minor"][0] > tab["major"][zen] / tab["minor"][zen]
    assert abs(np.cos(tab["pa"][0])) > 0.9  # major axis north-south


# ----------------------------------------------------------------------------- CLEAN

SRC_RA, SRC_DEC = np.deg2rad([20.0, 110.0, 200.0, 300.0]), np.deg2rad([10.0, 35.0, 60.0, 80.0])
SRC_FLUX = np.array([100.0, 60.0, 40.0, 80.0])
FILTERS = dict(filter_m1_lmin=40)  # m = 0, a_00 and m = 1, l > 40 filtered (the paper's kind)


@pytest.fixture(scope="module")
def dirty_sources(core_acc):
    """Noiseless point sources observed through the transfer matrices' normal equations."""
    from mmflow.imaging.solvers import solve_alm

    tel, acc = core_acc
    vecs = radec_to_vec(SRC_RA, SRC_DEC)
    truth = point_sources_alm(vecs, SRC_FLUX, LMAX)
    for m in acc.ms:  # r_m = B^H v with v = B a_true
        acc.rhs[m] = acc.full_gram(m) @ truth[m_slice(LMAX, m)]
    eps = 1e-3 * max(np.linalg.eigvalsh(acc.full_gram(m))[-1] for m in acc.ms)
    dirty = solve_alm(acc, eps, filters=FILTERS)
    ops = psf.block_operators(acc, eps, FILTERS)
    np.testing.assert_allclose(psf.observe_alm(ops, truth, LMAX), dirty, atol=1e-9 * np.abs(dirty).max())
    table = psf.psf_table(ops, LMAX, np.deg2rad(np.arange(-50.0, 90.1, 2.5)))
    return tel, vecs, dirty, ops, table


def _components_near(state, vec, radius):
    sel = np.arccos(np.clip(state.comp_vec @ vec, -1, 1)) < radius
    c = (state.comp_vec[sel] * state.comp_flux[sel, None]).sum(0)
    return state.comp_flux[sel].sum(), c / np.linalg.norm(c)


def _ring(nside, dec, width, away_from, min_dist):
    from mmflow.imaging.clean import dec_of_pixels

    pix = np.flatnonzero(np.abs(dec_of_pixels(nside) - dec) < width)
    v = np.array(healpy.pix2vec(nside, pix)).T
    return pix[np.arccos(np.clip(v @ away_from, -1, 1)) > min_dist]


def test_clean_recovers_point_sources_and_removes_the_ncp_rings(dirty_sources):
    from mmflow.imaging import clean

    tel, vecs, dirty, ops, table = dirty_sources
    opts = clean.CleanOptions(min_sep_deg=15.0, rel_threshold=3e-4, max_cycles=200)
    state, reason = clean.clean_alm(dirty, ops, LMAX, table, clean.never_seen_dec_min(tel.lat_rad), opts=opts)
    assert reason == "rel_threshold"
    fwhm = psf.interp_table(table, SRC_DEC, "major")
    for v, f, w in zip(vecs, SRC_FLUX, fwhm):
        flux, centroid = _components_near(state, v, w)
        assert flux == pytest.approx(f, rel=0.01)
        assert np.arccos(min(1.0, centroid @ v)) < 0.05 * w
    nside = 128
    dirty_map = healpy.alm2map(dirty, nside, lmax=LMAX)
    resid_map = healpy.alm2map(state.residual_alm, nside, lmax=LMAX)
    seen = clean.observed_mask(nside, clean.never_seen_dec_min(tel.lat_rad))
    brightest = dirty_map[seen].max()
    assert np.abs(resid_map[seen]).max() < 1e-3 * brightest
    # the m = 0 filter leaves a negative ring through the dec-80 source; CLEAN removes it
    ring = _ring(nside, SRC_DEC[3], np.deg2rad(1.0), vecs[3], 3 * fwhm[3])
    restored = clean.restore_map(resid_map, state.comp_vec, state.comp_flux, table)
    assert dirty_map[ring].mean() < -0.005 * brightest
    assert abs(restored[ring].mean()) < 0.02 * abs(dirty_map[ring].mean())
    assert abs(resid_map[ring].mean()) < 0.02 * abs(dirty_map[ring].mean())


def test_engine_path_cleans_from_the_normal_equations(dirty_sources, core_acc):
    from mmflow.imaging import clean

    tel, acc = core_acc
    eps = dirty_sources[3][5].eps
    opts = clean.CleanOptions(min_sep_deg=15.0, rel_threshold=1e-2, max_cycles=60)
    out = clean.clean_normal_equations(acc, eps, tel.lat_rad, FILTERS, opts=opts, dec_step_deg=5.0)
    np.testing.assert_allclose(out["dirty_alm"], dirty_sources[2], atol=1e-12 * np.abs(dirty_sources[2]).max())
    assert out["reason"] == "rel_threshold"
    v = dirty_sources[1][0]
    flux, _ = _components_near(out["state"], v, np.deg2rad(5.0))
    assert flux == pytest.approx(SRC_FLUX[0], rel=0.02)
    pk = healpy.vec2pix(out["nside"], *v)
    assert out["restored_map"][pk] > 10 * np.abs(out["residual_map"]).max()


def test_clean_stops_at_k_sigma_of_the_noise(dirty_sources):
    from mmflow.imaging import clean

    tel, _, dirty, ops, table = dirty_sources
    peak0 = healpy.alm2map(dirty, 128, lmax=LMAX).max()
    noise = peak0 / 300.0
    opts = clean.CleanOptions(min_sep_deg=15.0, k_sigma=3.0, max_cycles=200)
    state, reason = clean.clean_alm(dirty, ops, LMAX, table, clean.never_seen_dec_min(tel.lat_rad), noise, opts)
    assert reason == "threshold"
    assert state.peaks[-1] <= 3 * noise < state.peaks[-2]


def test_highpass_clean_recovers_sources_on_bright_smooth_emission(core_acc):
    from mmflow.imaging import clean
    from mmflow.sky.diffuse import band_limited_random_alm

    tel, acc = core_acc
    vecs = radec_to_vec(SRC_RA, SRC_DEC)
    smooth = healpy.resize_alm(3e3 * band_limited_random_alm(7, seed=5), 7, 7, LMAX, LMAX)  # l < 8 only
    truth = point_sources_alm(vecs, SRC_FLUX, LMAX) + smooth
    eps = 1e-3 * max(np.linalg.eigvalsh(acc.full_gram(m))[-1] for m in acc.ms)
    ops = psf.block_operators(acc, eps, FILTERS)
    dirty = psf.observe_alm(ops, truth, LMAX)  # = solve_alm of data B a_true (test above)
    assert healpy.alm2map(psf.observe_alm(ops, smooth, LMAX), 64, lmax=LMAX).max() > 0.15 * \
        healpy.alm2map(dirty - psf.observe_alm(ops, smooth, LMAX), 64, lmax=LMAX).max()  # bright smooth sky
    w = psf.highpass_weights(LMAX, 16, 8)
    assert w[7] == 0 and w[16] == 1 and 0 < w[12] < 1
    table = psf.psf_table(ops, LMAX, np.deg2rad(np.arange(-50.0, 90.1, 5.0)), weights=w)
    opts = clean.CleanOptions(min_sep_deg=15.0, rel_threshold=1e-3, max_cycles=150)
    state, reason = clean.clean_alm(dirty, ops, LMAX, table, clean.never_seen_dec_min(tel.lat_rad), opts=opts,
                                    weights=w)
    assert reason in ("rel_threshold", "stall")
    # Tikhonov's operator leaks ~12 % of the smooth sky's peak above l_cut into H dirty: with a
    # smooth sky 10x brighter the fluxes are off by up to 6 % (and by factors without high-pass)
    for v, f in zip(vecs, SRC_FLUX):
        assert _components_near(state, v, np.deg2rad(5.0))[0] == pytest.approx(f, rel=0.01)
    restored = clean.restore_highpass(dirty, state, table, w, LMAX, 128)
    low = healpy.map2alm(restored, lmax=7, iter=3)  # l < 8 never went through CLEAN
    ref = dirty[np.concatenate([np.arange(m_slice(LMAX, m).start, m_slice(LMAX, m).start + 8 - m)
                                for m in range(8)])]
    np.testing.assert_allclose(low, ref, atol=2e-3 * np.abs(ref).max())


def test_clean_resumes_from_a_checkpoint_and_blocks_give_the_same_answer(dirty_sources):
    from mmflow.imaging import clean

    tel, _, dirty, ops, table = dirty_sources
    nside, opts = 128, clean.CleanOptions(min_sep_deg=15.0)
    mask = clean.observed_mask(nside, clean.never_seen_dec_min(tel.lat_rad))
    s = clean.CleanState(dirty.copy())
    for _ in range(4):
        s, _ = clean.major_cycle(s, ops, LMAX, table, mask, nside, opts)
    saved = {k: np.array(v) for k, v in s.to_arrays().items()}  # as npz/zarr would
    a, _ = clean.major_cycle(s, ops, LMAX, table, mask, nside, opts)
    b, _ = clean.major_cycle(clean.CleanState.from_arrays(saved), ops, LMAX, table, mask, nside, opts, m_block=7)
    np.testing.assert_allclose(b.residual_alm, a.residual_alm, atol=1e-12 * np.abs(dirty).max())
    np.testing.assert_array_equal(b.comp_flux, a.comp_flux)
    assert a.cycle == b.cycle == 5 and a.comp_cycle.max() == 4
    # observing the model reproduces the subtracted part exactly
    np.testing.assert_allclose(dirty - psf.observe_alm(ops, a.model_alm(LMAX), LMAX), a.residual_alm,
                               atol=1e-9 * np.abs(dirty).max())


def test_peaks_respect_separation_and_the_declination_mask():
    from mmflow.imaging import clean

    nside = 128
    dec = clean.dec_of_pixels(nside)
    _, lat = healpy.pix2ang(nside, np.arange(healpy.nside2npix(nside)), lonlat=True)
    np.testing.assert_allclose(np.rad2deg(dec), lat, atol=1e-9)  # dec = pi/2 - theta, not acos(z)
    hmap = np.zeros(healpy.nside2npix(nside))
    pts = radec_to_vec(np.deg2rad([10.0, 12.5, 100.0, 200.0]), np.deg2rad([20.0, 20.0, -70.0, 50.0]))
    for v, amp in zip(pts, [5.0, 4.0, 9.0, 3.0]):
        hmap += amp * np.exp(-0.5 * (np.arccos(np.clip(np.array(healpy.pix2vec(nside, np.arange(len(hmap)))).T @ v,
                                                        -1, 1)) / np.deg2rad(0.6)) ** 2)
    mask = clean.observed_mask(nside, clean.never_seen_dec_min(np.deg2rad(37.2)))
    pix = clean.find_peaks(hmap, 10, np.deg2rad(3.0), mask, floor=0.1)
    got = np.array(healpy.pix2vec(nside, pix)).T
    assert len(pix) == 2  # the dec -70 peak is never seen; the 2-deg neighbour is within 3 deg
    vecs, vals = clean.refine_peaks(hmap, pix)
    np.testing.assert_allclose(np.arccos(np.clip(np.sum(vecs * pts[[0, 3]], 1), -1, 1)), 0, atol=np.deg2rad(0.1))
    assert np.all(np.arccos(np.clip(np.sum(got * pts[[0, 3]], 1), -1, 1)) < healpy.nside2resol(nside))
    assert vals[0] == pytest.approx(5.0, rel=0.02)


def test_restoring_beam_conserves_flux_and_follows_the_table():
    from mmflow.imaging import clean

    nside = 256
    table = {"dec": np.deg2rad([-90.0, 90.0]), "major": np.deg2rad([3.0, 3.0]), "minor": np.deg2rad([2.0, 2.0]),
             "pa": np.deg2rad([30.0, 30.0]), "peak": np.ones(2)}
    v = radec_to_vec(0.5, np.deg2rad(40.0))
    out = clean.restore_map(np.zeros(healpy.nside2npix(nside)), v[None], np.array([12.0]), table)
    assert out.sum() * healpy.nside2pixarea(nside) == pytest.approx(12.0, rel=1e-3)
    fit = psf.measure_beam(lambda q: out[healpy.vec2pix(nside, *q.T)], v, np.deg2rad(1.0), n_grid=61)
    assert fit["major"] == pytest.approx(np.deg2rad(3.0), rel=0.05)
    assert fit["pa"] == pytest.approx(np.deg2rad(30.0), abs=np.deg2rad(5.0))


def test_stop_reasons():
    from mmflow.imaging.clean import stop_reason

    assert stop_reason([]) is None
    assert stop_reason([10.0, 2.0], threshold=3.0) == "threshold"
    assert stop_reason([10.0, 5.0], threshold=3.0) is None
    assert stop_reason([10.0, 0.5], rel_threshold=0.01) is None
    assert stop_reason([10.0, 0.09], rel_threshold=0.01) == "rel_threshold"
    assert stop_reason([10.0] + [9.0] * 11, stall_cycles=10) == "stall"
    assert stop_reason(list(np.geomspace(10, 1, 12)), stall_cycles=10) is None
    assert stop_reason([5.0] * 4, max_cycles=3, stall_cycles=0) == "max_cycles"


def test_default_stall_ends_clean_on_residuals_points_do_not_describe():
    """The default stall (``CleanOptions``: the best peak must fall 10 % over 10 cycles) lets a point source
    CLEAN at its loop gain (0.85 a cycle: 80 % over 10 cycles) and sources of comparable brightness taken
    in turn (5 % a cycle) go on, and stops a residual that falls 1 % a cycle (the paper-scale run's
    peeling residuals around Cyg A and Cas A after ~90 cycles, docs/planning.md) within 11 cycles of it
    setting in; the configuration's default is the same."""
    from mmflow.imaging.clean import CleanOptions
    from mmflow.workflow.stages.clean.settings import CleanConfig

    opts = CleanOptions()
    assert CleanConfig().stall_fraction == opts.stall_frac and CleanConfig().stall_cycles == opts.stall_cycles
    point = 1e6 * 0.85 ** np.arange(60)
    assert all(opts.stop(point[:k], 0.0) is None for k in range(1, 61))
    crowded = 1e6 * 0.95 ** np.arange(60)
    assert all(opts.stop(crowded[:k], 0.0) is None for k in range(1, 61))
    slow = np.r_[point[:20], point[19] * 0.99 ** np.arange(1, 60)]
    first = next(k for k in range(1, len(slow) + 1) if opts.stop(slow[:k], 0.0) is not None)
    assert opts.stop(slow[:first], 0.0) == "stall" and 20 < first <= 31


def test_components_of_zero_flux_restore_nothing():
    """A Stokes parameter a CLEAN did not fit (the full-Stokes CLEAN's sources fitted in I alone carry Q = U =
    V = 0) restores to the residual itself; its zero components are left out of the merge (a pixel of only
    such had a 0 / 0 direction, on which healpy aborts the process)."""
    from mmflow.imaging.clean import merge_components, restore_map

    nside = 16
    v = np.array([radec_to_vec(0.3, 0.2), radec_to_vec(0.3, 0.2), radec_to_vec(2.0, -0.4)])
    vecs, flux = merge_components(v, np.array([0.0, 2.0, 0.0]), nside)
    np.testing.assert_allclose(vecs, v[1:2])
    np.testing.assert_allclose(flux, [2.0])
    table = {"dec": np.deg2rad([-90.0, 90.0]), "major": np.full(2, 0.1), "minor": np.full(2, 0.08),
             "pa": np.zeros(2)}
    residual = np.random.default_rng(0).normal(size=healpy.nside2npix(nside))
    np.testing.assert_array_equal(restore_map(residual, v, np.zeros(3), table), residual)
    restored = restore_map(residual, v, np.array([0.0, 2.0, 0.0]), table)
    pix = healpy.pixelfunc.vec2pix(nside, *v[1])
    peak = 2.0 / (2 * np.pi * (0.1 / psf.FWHM_PER_SIGMA) * (0.08 / psf.FWHM_PER_SIGMA))  # Jy/sr at the centre
    assert restored[pix] > residual[pix] + peak / 2


def test_a_blocks_point_columns_are_the_full_columns_rows_to_the_bit():
    """psf_columns of an m block computes only the block's m (``point_columns(..., m_start)``): the rows of the
    columns computed for every m up to the block's end, bit for bit, so a task's PSF no longer holds the
    columns of all the m before its block."""
    from mmflow.conventions import m_block_slice

    lmax = 60
    vecs = radec_to_vec(np.array([0.3, 2.0, 4.1]), np.array([-0.4, 0.2, 1.2]))
    for m0, m1 in ((0, 8), (24, 32), (56, 61)):
        full = psf.point_columns(vecs, lmax, m1)[m_block_slice(lmax, m0, m1)]
        np.testing.assert_array_equal(psf.point_columns(vecs, lmax, m1, m0), full)
