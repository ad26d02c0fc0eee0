"""PSF of Tikhonov m-mode maps and m-mode CLEAN (paper section 2.4)."""
import healpy
import numpy as np
import pytest
from scipy.special import eval_legendre

from mmflow.conventions import m_slice, radec_to_vec
from mmflow.imaging import psf
from mmflow.imaging.filters import filter_mask
from mmflow.mmode.engine import accumulate_normal_equations
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
    _, e, n = psf.tangent_basis(center)
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
