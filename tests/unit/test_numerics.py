"""Special functions at the paper's scale (lmax 1000) and beyond (2000), poles and equator included.

Every check compares with an independent answer: the addition theorem, closed forms at the
poles and the equator (log-gamma), scipy's ``sph_harm_y`` where it is finite, the package's
own Legendre recursion against ducc0's, Gauss-Legendre orthonormality, and adjointness.
See docs/numerics.md for the ranges these tests establish.
"""
import healpy
import numpy as np
import pytest
from scipy.special import gammaln, sph_harm_y

from mmflow.conventions import healpy_alm, unit_vectors
from mmflow.imaging.solvers import tikhonov
from mmflow.mmode.legendre import legendre_table
from mmflow.sky.diffuse import band_limited_random_alm, point_source_alm
from mmflow.sky.harmonics import point_sources_alm, synthesize_at, ylm_at
from mmflow.threads import single_threaded_blas

#: colatitudes: both poles, the equator, dec +45, a GL-like ring next to the pole, a random one
THETAS = (0.0, np.pi, np.pi / 2, np.pi / 4, 1.2e-3, np.pi - 1.2e-3, 1.234)


def _vecs(thetas, phi0=0.7):
    th = np.asarray(thetas, float)
    return unit_vectors(th, phi0 + 0.9 * np.arange(len(th)))


def _real_sky_dot(a, b, lmax):
    """``sum over all m of conj(a_lm) b_lm`` for real skies stored with m >= 0."""
    _, m = healpy.Alm.getlm(lmax)
    w = np.where(m > 0, 2.0, 1.0)
    return float(np.sum(w * (np.conj(a) * b).real))


def _per_l_power(y, lmax):
    """``sum over m = -l..l of |Y_lm|^2`` from the m >= 0 half (``|Y_{l,-m}| = |Y_lm|``)."""
    ell, m = healpy.Alm.getlm(lmax)
    w = np.where(m > 0, 2.0, 1.0)
    return np.bincount(ell, weights=w * np.abs(y) ** 2, minlength=lmax + 1)


@pytest.mark.parametrize("lmax", [1000, 2000])
def test_addition_theorem_for_every_l(lmax):
    ell = np.arange(lmax + 1)
    expected = (2 * ell + 1) / (4 * np.pi)
    for vec in _vecs(THETAS):
        a = point_sources_alm(vec[None], [1.0], lmax)
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(_per_l_power(a, lmax), expected, rtol=1e-10, atol=0)


def test_ylm_matches_scipy_where_scipy_is_finite():
    lmax = 100  # scipy's sph_harm_y is finite and accurate here (it is NaN from l ~ 646 on)
    ell, m = healpy.Alm.getlm(lmax)
    vecs = _vecs(THETAS)
    th = np.arccos(np.clip(vecs[:, 2], -1, 1))
    ph = np.arctan2(vecs[:, 1], vecs[:, 0])
    ref = sph_harm_y(ell[None, :], m[None, :], th[:, None], ph[:, None])
    np.testing.assert_allclose(ylm_at(vecs, lmax), ref, rtol=0, atol=1e-10)
    # mmax < lmax keeps healpy's layout for that (lmax, mmax)
    mmax = 17
    idx = np.arange(healpy.Alm.getsize(lmax, mmax))
    ell2, m2 = healpy.Alm.getlm(lmax, idx)
    ref2 = sph_harm_y(ell2[None, :], m2[None, :], th[:, None], ph[:, None])
    np.testing.assert_allclose(ylm_at(vecs, lmax, mmax), ref2, rtol=0, atol=1e-10)


def test_poles_and_equator_closed_forms_at_lmax_2000():
    """Y_l0(pole) = sqrt((2l+1)/4pi) (times (-1)^l at the south pole), Y_lm(pole) = 0 for m > 0;
    at the equator lambda_lm = 0 for odd l+m and otherwise, with l+m = 2p, l-m = 2q,
    ``|lambda_lm| = sqrt((2l+1)/4pi (l-m)!/(l+m)!) (2p-1)!!/(2q)!!``, sign ``(-1)^p``."""
    lmax = 2000
    ell, m = healpy.Alm.getlm(lmax)
    norm = np.sqrt((2 * ell + 1) / (4 * np.pi))
    north, south, equator = ylm_at(unit_vectors(np.array([0.0, np.pi, np.pi / 2]), 0.0), lmax)
    tol = 1e-11 * norm.max()  # ducc0's recursion: 5e-12 relative at l = 2000
    np.testing.assert_allclose(north, np.where(m == 0, norm, 0), rtol=0, atol=tol)
    np.testing.assert_allclose(south, np.where(m == 0, (-1.0) ** ell * norm, 0), rtol=0, atol=tol)
    p, q = (ell + m) // 2, (ell - m) // 2
    log_mag = (0.5 * (np.log((2 * ell + 1) / (4 * np.pi)) + gammaln(ell - m + 1) - gammaln(ell + m + 1))
               + gammaln(2 * p + 1) - p * np.log(2) - gammaln(p + 1)  # (2p-1)!! = (2p)!/(2^p p!)
               - q * np.log(2) - gammaln(q + 1))  # (2q)!! = 2^q q!
    ref = np.where((ell + m) % 2 == 0, (-1.0) ** p * np.exp(log_mag), 0.0)
    np.testing.assert_allclose(equator.real, ref, rtol=0, atol=1e-11 * norm.max())
    assert np.abs(equator.imag).max() == 0
    # the transfer matrices' Legendre tables give the same closed forms
    for mm in (0, 1, 700, 1999, 2000):
        t = legendre_table(mm, lmax, np.array([0.0, np.pi / 2, np.pi]))
        sel = m == mm
        np.testing.assert_allclose(t[:, 0], north.real[sel], rtol=0, atol=tol)
        np.testing.assert_allclose(t[:, 1], ref[sel], rtol=0, atol=tol)
        np.testing.assert_allclose(t[:, 2], south.real[sel], rtol=0, atol=tol)


@pytest.mark.parametrize("lmax", [1000, 2000])
def test_two_independent_recursions_agree(lmax):
    """ducc0's Legendre recursion (sky.harmonics) against mmode.legendre's scaled recursion."""
    vecs = _vecs(THETAS[2:])  # off the poles (the poles have closed forms above)
    y = ylm_at(vecs, lmax)
    th = np.arccos(np.clip(vecs[:, 2], -1, 1))
    ph = np.arctan2(vecs[:, 1], vecs[:, 0])
    ell, m = healpy.Alm.getlm(lmax)
    peak = np.sqrt((2 * lmax + 1) / (4 * np.pi))
    for mm in (0, 1, 3, lmax // 3, int(lmax / np.e), lmax // 2, lmax - 1, lmax):
        ours = legendre_table(mm, lmax, th).T * np.exp(1j * mm * ph)[:, None]
        # 1e-9 of the largest value: near the pole, cos(theta) rounding limits both to ~l^2 eps / theta^2
        np.testing.assert_allclose(y[:, m == mm], ours, rtol=0, atol=1e-9 * peak)


@pytest.mark.parametrize("lmax", [1000, 2000])
def test_legendre_tables_are_orthonormal_under_gauss_legendre_quadrature(lmax):
    """``sum_k w_k lambda_lm(theta_k) lambda_l'm(theta_k) = delta_ll' / (2 pi)`` on lmax+1 GL rings
    (exact for polynomials of degree 2 lmax + 1), for m across the range where ``sin^m theta``
    starts below float64's range (m ~ lmax / e) and at the pole rings."""
    import ducc0

    n = lmax + 1
    theta = ducc0.misc.GL_thetas(n)
    w = ducc0.misc.GL_weights(n, 1)  # includes 2 pi
    for m in (0, 2, lmax // 4, int(lmax / np.e), lmax // 2, lmax):
        t = legendre_table(m, lmax, theta)
        assert np.all(np.isfinite(t))
        gram = (t * w) @ t.T
        np.testing.assert_allclose(gram, np.eye(lmax - m + 1), rtol=0, atol=1e-11)


def test_point_source_alm_at_lmax_1000_is_finite_and_peaks_at_the_source():
    lmax = 1000
    src = unit_vectors(np.deg2rad(45.0), 1.3)  # dec +45
    alm = point_source_alm(src, 2.5, lmax)
    assert np.all(np.isfinite(alm))
    assert np.abs(alm[healpy.Alm.getidx(lmax, np.arange(646, lmax + 1), 3)]).min() > 0  # was NaN
    # value at the source: 2.5 sum_l (2l+1)/4pi = 2.5 (lmax+1)^2 / 4pi (addition theorem)
    at_src = synthesize_at(alm, src[None], lmax)[0]
    np.testing.assert_allclose(at_src, 2.5 * (lmax + 1) ** 2 / (4 * np.pi), rtol=1e-10)
    # healpy's synthesis (independent) peaks in the pixel holding the source
    nside = 512
    hmap = healpy.alm2map(alm, nside, lmax=lmax)
    assert np.all(np.isfinite(hmap))
    peak_vec = np.array(healpy.pix2vec(nside, int(np.argmax(hmap))))
    assert np.arccos(np.clip(peak_vec @ src, -1, 1)) < healpy.max_pixrad(nside)
    # and synthesize_at agrees with healpy at pixel centres near the source
    pix = healpy.query_disc(nside, src, np.deg2rad(1.0))[::7]
    pv = np.array(healpy.pix2vec(nside, pix)).T
    np.testing.assert_allclose(synthesize_at(alm, pv, lmax), hmap[pix], rtol=0, atol=1e-9 * at_src)


def test_many_sources_are_the_sum_of_single_sources():
    """Linearity across the chunk boundary (512 points) and at mmax < lmax."""
    lmax, rng = 120, np.random.default_rng(3)
    vecs = rng.normal(size=(700, 3))
    vecs[:2] = [[0, 0, 5.0], [0, 0, -1.0]]  # unnormalised on purpose; both poles
    flux = rng.normal(size=700)
    total = point_sources_alm(vecs, flux, lmax)
    single = ylm_at(vecs, lmax).conj().T @ flux
    np.testing.assert_allclose(total, single, rtol=0, atol=1e-11 * np.abs(total).max())
    part = point_sources_alm(vecs, flux, lmax, mmax=30)
    np.testing.assert_allclose(part, total[: healpy.Alm.getsize(lmax, 30)], rtol=0, atol=1e-12 * np.abs(total).max())


def test_an_m_block_of_point_sources_alm_is_the_full_one_to_the_bit():
    """A CLEAN cycle's m block (``mmin``) at the paper's lmax: the coefficients of the full layout from
    ``(mmin, mmin)`` on, bit for bit (each m its own recursion), and none beyond ``mmax``."""
    from mmflow.conventions import m_block_slice
    from mmflow.imaging.clean import component_alm

    rng = np.random.default_rng(5)
    vecs, flux = rng.normal(size=(40, 3)), rng.normal(size=40)
    lmax = 1000
    full = point_sources_alm(vecs, flux, lmax)
    for m0, m1 in [(0, 16), (16, 32), (496, 512), (992, 1001), (1000, 1001)]:
        block = point_sources_alm(vecs, flux, lmax, m1 - 1, m0)
        np.testing.assert_array_equal(block, full[m_block_slice(lmax, m0, m1)])
        np.testing.assert_array_equal(component_alm(vecs, flux, lmax, m1, m0), block)
    assert component_alm(vecs[:0], flux[:0], lmax, 32, 16).shape == block_size(lmax, 16, 32)
    with pytest.raises(ValueError, match="mmin"):
        point_sources_alm(vecs, flux, lmax, 10, 11)


def block_size(lmax, m0, m1):
    from mmflow.conventions import m_block_slice

    sl = m_block_slice(lmax, m0, m1)
    return (sl.stop - sl.start,)


@pytest.mark.parametrize("lmax, n", [(300, 700), (1000, 40)])
def test_synthesize_at_is_the_adjoint_of_point_sources_alm(lmax, n):
    rng = np.random.default_rng(lmax)
    vecs = rng.normal(size=(n, 3))
    vecs[0] = [0, 0, 1.0]
    f = rng.normal(size=n)
    b = band_limited_random_alm(lmax, seed=lmax, power_index=0.0)
    lhs = _real_sky_dot(point_sources_alm(vecs, f, lmax), b, lmax)
    rhs = f @ synthesize_at(b, vecs, lmax)
    assert abs(lhs - rhs) < 1e-11 * np.sqrt(np.sum(f**2) * _real_sky_dot(b, b, lmax)) * lmax


def test_psf_at_lmax_700_from_a_synthetic_gram_is_finite_and_peaks_at_the_source():
    """PSF alm per m: ``(G_m + eps I)^-1 G_m a_ps`` with ``G_m = diag(g_l) + U U^T`` (a beam-like
    response falling with l plus a small random rank-2 coupling), solved with the package's
    Tikhonov solver. With ``U = 0`` the PSF at the source is ``sum_l (2l+1)/4pi g_l/(g_l+eps)``."""
    lmax, eps = 700, 0.05
    rng = np.random.default_rng(7)
    src = unit_vectors(np.deg2rad(40.0), 2.0)
    a_ps = point_sources_alm(src[None], [1.0], lmax)
    ell_all = np.arange(lmax + 1)
    g_l = np.exp(-((ell_all / 450.0) ** 2))
    ell, _ = healpy.Alm.getlm(lmax)
    psf = np.zeros_like(a_ps)
    with single_threaded_blas():  # many small factorisations: BLAS threads only add contention
        for m in range(lmax + 1):
            sl = slice(healpy.Alm.getidx(lmax, m, m), healpy.Alm.getidx(lmax, lmax, m) + 1)
            d = g_l[m:]
            u = 0.02 * rng.normal(size=(len(d), 2)) * np.sqrt(d)[:, None]
            gram = u @ u.T
            gram[np.diag_indices_from(gram)] += d  # real symmetric: real and imaginary parts as two columns
            rhs = gram @ np.stack([a_ps[sl].real, a_ps[sl].imag], axis=1)
            sol, _ = tikhonov(gram, rhs, eps)
            psf[sl] = sol[:, 0] + 1j * sol[:, 1]
    assert np.all(np.isfinite(psf))
    expected_peak = np.sum((2 * ell_all + 1) / (4 * np.pi) * g_l / (g_l + eps))
    psf_diag = g_l[ell] / (g_l[ell] + eps) * a_ps  # the U = 0 answer
    np.testing.assert_allclose(synthesize_at(psf_diag, src[None], lmax)[0], expected_peak, rtol=1e-10)
    nside = 512
    hmap = healpy.alm2map(psf, nside, lmax=lmax)
    assert np.all(np.isfinite(hmap))
    peak_vec = np.array(healpy.pix2vec(nside, int(np.argmax(hmap))))
    assert np.arccos(np.clip(peak_vec @ src, -1, 1)) < healpy.max_pixrad(nside)
    assert abs(hmap.max() / expected_peak - 1) < 0.05


def test_transfer_coefficients_at_lmax_1000_match_an_independent_harmonic_analysis():
    """``B_lm(b) = int A exp(2 pi i b.r) Y_lm dOmega`` from the package's transfer matrices (its
    Legendre tables, pole rings included) against ducc0's adjoint synthesis of ``f_b`` on a
    finer Gauss-Legendre grid: with ``f = f_r + i f_i``, ``B_lm = conj(alm(f_r) - i alm(f_i))``."""
    import ducc0

    from mmflow.conventions import enu_to_equatorial_matrix
    from mmflow.mmode.transfer import fringe_bandlimit, make_grid, transfer_blocks
    from mmflow.telescope.beams import GaussianBeam

    lmax, lat, freq = 1000, np.deg2rad(37.24), 50e6
    beam = GaussianBeam(30)
    b = np.array([[120.0, -60.0, 5.0]])  # 2 pi |b| ~ 840: coefficients up to l ~ 900
    grid = make_grid(lat, beam, freq, lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), beam.lmax_hint))
    blocks = transfer_blocks(grid, b)
    nt, nph = 1100, 2400
    th = ducc0.misc.GL_thetas(nt)
    w = ducc0.misc.GL_weights(nt, nph)
    vec = unit_vectors(th[:, None], (2 * np.pi * np.arange(nph) / nph)[None, :])
    f = beam.power_enu(vec @ enu_to_equatorial_matrix(lat), freq) * np.exp(2j * np.pi * (vec @ b[0]))
    # adjoint_synthesis_2d sums map * conj(Y_lm) over the grid: the quadrature weights go in the map
    alm = [ducc0.sht.adjoint_synthesis_2d(map=(w[:, None] * part)[None], spin=0, lmax=lmax,
                                          geometry="GL", nthreads=1)[0] for part in (f.real, f.imag)]
    ref = np.conj(alm[0] - 1j * alm[1])
    ours = np.concatenate([blk[0] for blk in blocks])  # m-major, l = m..lmax: healpy's layout
    assert np.all(np.isfinite(ours))
    peak = np.abs(ref).max()
    assert np.abs(ref[healpy.Alm.getidx(lmax, np.arange(800, 900), 0)]).max() > 1e-3 * peak  # high l populated
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-9 * peak)


def test_alm_rotation_moves_point_sources():
    """``frames.rotate_alm`` (healpy's Wigner rotation): the rotated a_lm of point sources are the
    a_lm of the rotated points. lmax 300 here (healpy's rotation costs ~30 s at lmax 1000, where
    it was checked once the same way; docs/numerics.md)."""
    from mmflow.sky.frames import rotate_alm
    from scipy.spatial.transform import Rotation

    lmax = 300
    vecs = _vecs((0.0, np.pi / 2, 0.4, 2.9))
    flux = np.array([1.0, -2.0, 0.5, 3.0])
    rot = Rotation.from_euler("zyz", [0.3, 1.1, -0.7]).as_matrix()
    got = rotate_alm(point_sources_alm(vecs, flux, lmax), rot, lmax)
    want = point_sources_alm(vecs @ rot.T, flux, lmax)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * np.abs(want).max())


def test_beams_are_finite_at_zenith_poles_and_horizon():
    """Every beam model at the exact zenith (az = atan2(0, 0)), just above and below the horizon,
    and on the transfer grid of lmax 2000 (rings within 3e-3 rad of both celestial poles):
    finite, non-negative, 1 at zenith (analytic and Zernike), 0 below the horizon."""
    from mmflow.mmode.transfer import make_grid
    from mmflow.telescope.beams import GaussianBeam, SinElevationBeam, ZernikeBeam

    gauss = GaussianBeam(40)
    beams = [SinElevationBeam(1.5), gauss, ZernikeBeam.fit(gauss, [50e6, 60e6])]
    enu = np.array([[0, 0, 1.0], [0, 1, 1e-12], [1, 0, -1e-12], [0, 0, -1.0]])
    for beam in beams:
        a = beam.power_enu(enu, 55e6)
        assert np.all(np.isfinite(a)) and np.all(a >= 0)
        np.testing.assert_allclose(a[0], 1.0, rtol=1e-12)
        assert a[2] == 0 and a[3] == 0
        grid = make_grid(np.deg2rad(37.24), beam, 55e6, 2000, beam.lmax_hint)
        assert grid.theta[0] < 3e-3 and np.pi - grid.theta[-1] < 3e-3
        assert np.all(np.isfinite(grid.beam)) and np.all(grid.beam >= 0)
        assert grid.beam.max() <= 1.0 + 1e-9


def test_rotate_alm_equals_healpy_and_moves_a_point_source():
    """ducc0's Wigner rotation (used by mmflow) against healpy's, and a point source lands where R sends it."""
    import healpy

    from mmflow.sky.frames import rotate_alm, rotation_matrix
    from mmflow.sky.harmonics import point_sources_alm, synthesize_at

    lmax = 96
    rng = np.random.default_rng(5)
    alm = (rng.normal(size=healpy.Alm.getsize(lmax)) + 1j * rng.normal(size=healpy.Alm.getsize(lmax)))
    alm[:lmax + 1] = alm[:lmax + 1].real
    for mat in (rotation_matrix("icrs", "galactic", 2457802.0), np.eye(3),
                np.array([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]])):  # theta = pi: gimbal lock
        ref = alm.copy()
        healpy.rotate_alm(ref, matrix=mat, lmax=lmax)
        np.testing.assert_allclose(rotate_alm(alm, mat, lmax), ref, atol=1e-12 * np.abs(ref).max())
    lmax = 1000
    mat = rotation_matrix("date", "galactic", 2461000.5)
    v = np.array([0.3, -0.5, 0.81])
    v /= np.linalg.norm(v)
    out = rotate_alm(point_sources_alm(v[None], np.ones(1), lmax), mat, lmax)
    here, elsewhere = synthesize_at(out, np.stack([mat @ v, v]), lmax)
    assert np.isclose(here, ((lmax + 1) ** 2) / (4 * np.pi), rtol=1e-9) and abs(elsewhere) < 1e-3 * here


def test_ml_array_to_healpy_layout_uses_healpys_index_and_pads_unmeasured_m_with_zero():
    """``healpy_alm`` puts ``a[m, l]`` at ``healpy.Alm.getidx(lmax, l, m)``; rows beyond mmax and
    columns beyond lmax (a wider array) are not copied; padding below the diagonal is ignored."""
    lmax, mmax = 6, 3
    m, ell = np.meshgrid(np.arange(lmax + 3), np.arange(lmax + 3), indexing="ij")
    a = (100 * m + ell + 1j * ell).astype(np.complex128)  # a[m, l] names its (l, m); padding l < m too
    out = healpy_alm(a, lmax, mmax)
    assert out.shape == (healpy.Alm.getsize(lmax),) and out.dtype == np.complex128
    for mm in range(lmax + 1):
        for ll in range(mm, lmax + 1):
            assert out[healpy.Alm.getidx(lmax, ll, mm)] == (a[mm, ll] if mm <= mmax else 0)
    # without mmax every row the array has (up to lmax) is copied
    assert np.array_equal(healpy_alm(a[:mmax + 1, :lmax + 1], lmax), out)
    assert np.array_equal(healpy_alm(a, lmax)[healpy.Alm.getidx(lmax, lmax, lmax)], a[lmax, lmax])
