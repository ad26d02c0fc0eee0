"""Full-Stokes transfer coefficients (issue 22 kernels): Jones beams, IAU conventions, quadrature.

The brute force builds the coherency ``S`` as a 3x3 Cartesian tensor from north/east vectors
derived here (not :func:`mmflow.mmode.polarised.feed_projections`), forms ``J_p S J_q^H`` directly
(not through the K kernels) and sums on a HEALPix grid; E/B harmonics come from healpy's
synthesis (its spin-2 convention defines E and B; ``U_IAU = -U_healpy``).
"""
import healpy as hp
import numpy as np
import pytest
from scipy.special import sph_harm_y

from mmflow.conventions import enu_to_equatorial_matrix
from mmflow.errors import InputError
from mmflow.mmode.polarised import (CORRELATIONS, feed_projections, make_polarised_grid, polarised_coefficients,
                                    stokes_kernels)
from mmflow.mmode.polarised_transfer import polarised_pass, polarised_transfer_blocks
from mmflow.mmode.transfer import fringe_bandlimit, make_grid, transfer_blocks
from mmflow.telescope.jones import PyUVDataJones, ShortDipoleJones

LAT = np.deg2rad(37.24)
FREQ = 50e6
FEED = {"x": 0, "y": 1}


def _grid(jones, b, lmax):
    return make_polarised_grid(LAT, jones, FREQ, lmax, fringe_bandlimit(np.linalg.norm(b, axis=-1).ravel(),
                                                                        jones.lmax_hint))


def test_short_dipole_matches_pyuvdata_efield_and_power():
    from pyuvdata import BeamInterface
    from pyuvdata.analytic_beam import ShortDipoleBeam

    rng = np.random.default_rng(0)
    az, za = rng.uniform(0, 2 * np.pi, 200), rng.uniform(0, np.pi / 2 * 0.99, 200)
    ours = ShortDipoleJones()
    ref = BeamInterface(ShortDipoleBeam(), beam_type="efield").compute_response(
        az_array=(np.pi / 2 - az) % (2 * np.pi), za_array=za, freq_array=np.array([FREQ]))[:, :, 0]
    j = ours.jones(az, za, FREQ)
    np.testing.assert_allclose(j[:, 0], ref[1], atol=1e-12)  # e_theta = pyuvdata's za_hat
    np.testing.assert_allclose(j[:, 1], ref[0], atol=1e-12)  # e_phi = pyuvdata's az_hat
    # x is the east dipole: no response to an E-field along east from the east horizon
    enu = ours.jones_enu(np.array([1.0, 0.0, 1e-9]) / np.hypot(1, 1e-9), FREQ)
    assert abs(enu[0, 0]) < 1e-6 and abs(enu[1, 1]) > 0.99
    # the derived Stokes-I power beam is the existing pyuvdata power beam (XX + YY) / 2
    from mmflow.telescope.beams import PyUVDataBeam
    np.testing.assert_allclose(ours.power_beam().power(az, za, FREQ),
                               PyUVDataBeam(ShortDipoleBeam()).power(az, za, FREQ), atol=1e-12)
    np.testing.assert_allclose(ours.power(az, za, FREQ), 1 - np.sin(za) ** 2 / 2, atol=1e-12)


def test_uvbeam_efield_wrapper_interpolates_the_dipole():
    from pyuvdata.analytic_beam import ShortDipoleBeam

    uvb = ShortDipoleBeam(x_orientation="north").to_uvbeam(
        freq_array=np.array([FREQ]), beam_type="efield",
        axis1_array=np.deg2rad(np.arange(0, 360, 1.0)), axis2_array=np.deg2rad(np.arange(0, 91, 1.0)))
    wrapped = PyUVDataJones(uvb)
    assert wrapped.feed_index == (1, 0)  # its "y" is east: mmflow's x
    rng = np.random.default_rng(1)
    az, za = rng.uniform(0, 2 * np.pi, 100), rng.uniform(0, 1.4, 100)
    np.testing.assert_allclose(wrapped.jones(az, za, FREQ), ShortDipoleJones().jones(az, za, FREQ), atol=2e-4)
    # an analytic pyuvdata beam is evaluated, not interpolated
    np.testing.assert_allclose(PyUVDataJones(ShortDipoleBeam()).jones(az, za, FREQ),
                               ShortDipoleJones().jones(az, za, FREQ), atol=1e-12)
    power = ShortDipoleBeam().to_uvbeam(freq_array=np.array([FREQ]), beam_type="power",
                                        axis1_array=np.deg2rad(np.arange(0, 360, 10.0)),
                                        axis2_array=np.deg2rad(np.arange(0, 91, 10.0)))
    with pytest.raises(InputError, match="E-field"):
        PyUVDataJones(power)


def test_iau_convention_at_zenith():
    """At zenith x (east) sees E_E, y (north) E_N: V_yy = I + Q, V_xx = I - Q, V_xy = <E_E E_N*> = U + iV.

    (IAU +V, the field turning north through east, under mmflow's fringe ``exp(+2 pi i b.r)``:
    phasor ``(A_N, A_E) = (1, i)`` of ``Re[A exp(-i w t)]``, so ``<E_E E_N*> = +i``; before issue 39
    this asserted U - iV, the sign of the opposite fringe. tests/unit/imaging/test_stokes_sign.py checks
    it against fields written in the time domain.)"""
    zen = enu_to_equatorial_matrix(LAT) @ np.array([0.0, 0.0, 1.0])
    jn, je = feed_projections(ShortDipoleJones(), LAT, zen[None], FREQ)
    stokes = np.array([1.0, 0.3, 0.2, 0.1])  # I, Q, U, V
    resp = {c: np.array(stokes_kernels(jn, je, c))[:, 0] @ stokes for c in CORRELATIONS}
    np.testing.assert_allclose([resp["yy"], resp["xx"], resp["xy"], resp["yx"]],
                               [1.3, 0.7, 0.2 + 0.1j, 0.2 - 0.1j], atol=1e-12)


def test_unpolarised_T_coefficients_equal_the_stokes_I_path():
    """(b^{xx,T} + b^{yy,T}) / 2 is the scalar B_lm of the derived power beam (the pure pyuvdata dipole)."""
    jones = ShortDipoleJones()
    b = np.array([[3.0, -2.0, 0.5], [0.0, 0.0, 0.0], [-4.0, 1.5, -0.3]])
    lmax = 30
    fl = fringe_bandlimit(np.linalg.norm(b, axis=1), jones.lmax_hint)
    pol = polarised_transfer_blocks(make_polarised_grid(LAT, jones, FREQ, lmax, fl), b, ("xx", "yy"))
    scalar = transfer_blocks(make_grid(LAT, jones.power_beam(), FREQ, lmax, fl), b)
    peak = max(np.abs(x).max() for x in scalar)
    for m in range(lmax + 1):
        t = 0.5 * (pol[m][0, 0] + pol[m][1, 0])
        assert np.abs(t - scalar[m]).max() < 1e-3 * peak
    assert max(np.abs(0.5 * (p[0, 0] + p[1, 0]) - s).max() for p, s in zip(pol, scalar)) < 1e-10 * peak


def _north_east(vec):
    """Celestial north and east unit vectors from their definition (towards the pole; east = north x r)."""
    z = np.array([0.0, 0.0, 1.0])
    n = z - vec[:, 2:3] * vec
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n, np.cross(n, vec)


def _healpix(nside):
    th, ph = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    vec = np.stack(hp.pix2vec(nside, np.arange(hp.nside2npix(nside))), axis=-1)
    return th, ph, vec, 4 * np.pi / len(th)


def _feeds_on_sky(jones, vec, phi=0.0):
    """Cartesian (celestial) J_p of both feeds at each pixel with the array at sidereal angle phi,
    dotted with north and east: ``[feed, N/E, pix]``."""
    mat = enu_to_equatorial_matrix(LAT, phi)
    jeq = np.einsum("ik,pkn->pni", mat, jones.jones_enu(vec @ mat, FREQ))  # (feed, pix, 3)
    n, e = _north_east(vec)
    return np.stack([np.sum(jeq * n, axis=-1), np.sum(jeq * e, axis=-1)], axis=1)


class _TwistedDipoles(ShortDipoleJones):
    """Short dipoles with complex, direction-dependent phases on each component (no symmetry to lean on)."""

    def _jones(self, az, za, freq_hz):
        out = super()._jones(az, za, freq_hz)
        return out * np.exp(1j * np.array([[0.3 + az, -1.1 * za], [2.0 * za - az, 0.7 + 0.0 * az]]))


@pytest.mark.parametrize("jones", [ShortDipoleJones(), ShortDipoleJones(horizon_taper=3.0), _TwistedDipoles()],
                         ids=["dipole", "tapered", "complex"])
def test_feed_projections_are_the_feeds_rotated_to_the_sky_and_projected_on_north_and_east(jones):
    """``feed_projections`` (four real overlaps per point) equals the definition computed independently: each
    feed's ENU response vector rotated to the celestial frame and dotted with north and east from their
    definition (:func:`_feeds_on_sky`), at every HEALPix pixel and four sidereal angles; at the celestial poles
    (where north is undefined) it is finite and takes the basis of ``phi = 0``, as ``arctan2(0, 0)`` does."""
    _, _, vec, _ = _healpix(16)
    for phi in (0.0, 0.9, 2.5, 4.4):
        jn, je = feed_projections(jones, LAT, vec, FREQ, phi)
        ref = _feeds_on_sky(jones, vec, phi)
        np.testing.assert_allclose(jn, ref[:, 0], atol=1e-12)
        np.testing.assert_allclose(je, ref[:, 1], atol=1e-12)
    pole = feed_projections(jones, LAT, np.array([[0.0, 0.0, 1.0]]), FREQ)
    near = feed_projections(jones, LAT, np.array([[1e-9, 0.0, 1.0]]) / np.hypot(1e-9, 1.0), FREQ)
    assert np.all(np.isfinite(pole)) and np.allclose(pole, near, atol=1e-8)


def _brute_visibility(feeds, fringe_domega, corr, stokes):
    """sum_pix J_p S J_q^H e^{2 pi i b.r} dOmega, S = [[I + Q, U - iV], [U + iV, I - Q]] on (north, east)
    (IAU V under this fringe: docs/conventions.md)."""
    i, q, u, v = stokes
    (pn, pe), (qn, qe) = feeds[FEED[corr[0]]], np.conj(feeds[FEED[corr[1]]])
    resp = pn * (i + q) * qn + pn * (u - 1j * v) * qe + pe * (u + 1j * v) * qn + pe * (i - q) * qe
    return np.sum(resp * fringe_domega)


def _eb_maps(nside, lmax, l, m, value, which):
    """IAU (Q, U) of the real sky with E_lm (or B_lm) = value and its m -> -m partner."""
    alm = np.zeros((3, hp.Alm.getsize(lmax)), complex)
    alm[1 if which == "E" else 2, hp.Alm.getidx(lmax, l, m)] = value
    _, q, u_healpy = hp.alm2map(alm, nside, lmax=lmax)
    return q, -u_healpy


@pytest.mark.parametrize("seed", [0, 1])
def test_coefficients_match_brute_force_quadrature(seed):
    """b^X_lm for X = T, E, B, V (both signs of m) against a direct HEALPix sum of the definition."""
    jones = ShortDipoleJones(horizon_taper=3.0)
    rng = np.random.default_rng(seed)
    lmax, nside = 24, 256
    th, ph, vec, dom = _healpix(nside)
    feeds = _feeds_on_sky(jones, vec)
    for _ in range(2):
        b = rng.uniform(-3, 3, 3)
        grid = _grid(jones, b[None], lmax)
        fringe = np.exp(2j * np.pi * vec @ b) * dom
        corr = CORRELATIONS[int(rng.integers(4))]
        coef = polarised_coefficients(grid, b, corr)
        scale = np.abs(coef).max()
        l = int(rng.integers(3, lmax + 1))
        m = int(rng.integers(1, l + 1))
        for x, stokes_of in (("T", lambda y: (y, 0, 0, 0)), ("V", lambda y: (0, 0, 0, y))):
            for mm in (m, -m):
                ylm = sph_harm_y(l, mm, th, ph)
                ref = _brute_visibility(feeds, fringe, corr, stokes_of(ylm))
                got = coef["TEBV".index(x), l, lmax + mm]
                assert abs(got - ref) < 1e-3 * max(abs(ref), 1e-3 * scale), (x, l, mm, corr, got, ref)
        for x in ("E", "B"):
            v1, v2 = (_brute_visibility(feeds, fringe, corr, (0, *_eb_maps(nside, lmax, l, m, c, x), 0))
                      for c in (1.0, 1j))
            got_p = coef["TEBV".index(x), l, lmax + m]
            got_m = (-1) ** m * coef["TEBV".index(x), l, lmax - m]
            for got, ref in ((got_p, (v1 - 1j * v2) / 2), (got_m, (v1 + 1j * v2) / 2)):
                assert abs(got - ref) < 1e-3 * max(abs(ref), 1e-3 * scale), (x, l, m, corr, got, ref)


def test_minus_m_row_is_plus_m_row_of_reversed_correlation_and_baseline():
    jones = ShortDipoleJones(horizon_taper=1.0)
    b = np.array([[2.0, -1.0, 0.4]])
    grid = _grid(jones, b, 16)
    fwd = polarised_transfer_blocks(grid, b, ("xy", "yx", "xx"))
    rev = polarised_transfer_blocks(grid, -b, ("yx", "xy", "xx"))
    peak = max(np.abs(x).max() for x in fwd)
    for m in range(1, 17):
        assert np.abs(fwd[m][:, :, 1:] - rev[m][:, :, :1]).max() < 1e-12 * peak


def _mmodes_of_skies(jones, b_enu_wl, skies, nside, n_lst):
    """m-modes ``[sky, m, corr]`` of the four correlations of each (I, Q, U, V) sky, by rotating the
    *array* (its feeds and baseline at sidereal angle phi) over the fixed sky."""
    _, _, vec, dom = _healpix(nside)
    vis = np.zeros((len(skies), n_lst, len(CORRELATIONS)), complex)
    for n, p in enumerate(2 * np.pi * np.arange(n_lst) / n_lst):
        feeds = _feeds_on_sky(jones, vec, p)
        fringe = np.exp(2j * np.pi * vec @ (enu_to_equatorial_matrix(LAT, p) @ b_enu_wl)) * dom
        for s, sky in enumerate(skies):
            vis[s, n] = [_brute_visibility(feeds, fringe, c, sky) for c in CORRELATIONS]
    return np.fft.fft(vis, axis=1) / n_lst  # V_m = (1/N) sum_n V(phi_n) e^{-i m phi_n}


def test_pure_E_sky_is_seen_through_E_coefficients_only():
    """A spin-2 sky of E harmonics only: the drift-scan m-modes equal sum_l b^E E_lm; the same sky
    as B harmonics through b^B; swapping them is wrong at O(1)."""
    jones = ShortDipoleJones(horizon_taper=3.0)
    lmax, nside, n_lst = 12, 128, 26  # n_lst > 2 lmax: the m-modes of a band-limited sky are exact
    rng = np.random.default_rng(3)
    alm = rng.normal(size=hp.Alm.getsize(lmax)) + 1j * rng.normal(size=hp.Alm.getsize(lmax))
    alm[:lmax + 1] = alm[:lmax + 1].real
    alm[hp.Alm.getidx(lmax, np.arange(2), np.zeros(2, int))] = 0
    alm[hp.Alm.getidx(lmax, 1, 1)] = 0
    b_enu = np.array([2.5, -1.0, 0.1])
    b_eq = enu_to_equatorial_matrix(LAT) @ b_enu
    blocks = polarised_transfer_blocks(_grid(jones, b_eq[None], lmax), b_eq[None])
    zero = np.zeros_like(alm)
    skies = []
    for which in ("E", "B"):
        _, q, u_h = hp.alm2map([zero, alm, zero] if which == "E" else [zero, zero, alm], nside, lmax=lmax)
        skies.append((0, q, -u_h, 0))
    for which, mm in zip(("E", "B"), _mmodes_of_skies(jones, b_enu, skies, nside, n_lst)):
        for m in range(lmax + 1):
            a = alm[hp.Alm.getidx(lmax, np.arange(m, lmax + 1), m)]
            blk = blocks[m]  # (corr, X, rows, l)
            for x, expect_match in (("E", which == "E"), ("B", which == "B")):
                pred = blk[:, "TEBV".index(x)] @ a  # (corr, rows)
                sim = mm[m][:, None] if m == 0 else np.stack([mm[m], np.conj(mm[-m])], axis=1)
                err = np.abs(pred - sim).max() / np.abs(sim).max()
                if expect_match:
                    assert err < 1e-3, (which, x, m, err)
                elif m == 3:
                    assert err > 0.1, (which, x, m, err)


def test_pure_V_sky_gives_antisymmetric_cross_hands_and_no_parallel_hands():
    """Short dipoles have real J: V leaks into no parallel hand and b^{xy,V} = -b^{yx,V}."""
    jones = ShortDipoleJones()
    b = np.array([[3.0, 1.0, -0.5], [0.0, 0.0, 0.0]])
    blocks = polarised_transfer_blocks(_grid(jones, b, 20), b)
    peak = max(np.abs(blk[2:, 3]).max() for blk in blocks)
    assert peak > 1e-3
    for blk in blocks:
        xx, yy, xy, yx = blk[:, 3]
        assert np.abs(xx).max() < 1e-12 * peak and np.abs(yy).max() < 1e-12 * peak
        assert np.abs(xy + yx).max() < 1e-12 * peak


@pytest.mark.parametrize("lmax_pol", [7, 8])  # the band limit's first row above it odd and even in l - m
def test_a_polarised_band_limit_keeps_t_and_the_rows_below_it(lmax_pol):
    """``lmax_pol`` (``imaging.stokes_lmax``) changes no T coefficient and no E, B, V coefficient at
    ``l <= lmax_pol``, and zeroes E, B, V above it: the same blocks as every Stokes parameter to lmax
    (there the (I, V) pair takes one GEMM per parity; below lmax the rows above the band limit take
    the I kernels alone)."""
    jones = ShortDipoleJones(horizon_taper=3.0)
    lmax = 20
    b = np.array([[3.0, 1.0, -0.5], [-1.2, 2.2, 0.4], [0.7, -0.3, 0.2]])
    grid = _grid(jones, b, lmax)
    full = polarised_pass(grid, b, lambda m, blk: blk.copy())
    low = polarised_pass(grid, b, lambda m, blk: blk.copy(), lmax_pol=lmax_pol)
    scale = max(np.abs(f).max() for f in full)
    for m, (f, lo) in enumerate(zip(full, low)):
        n_p = max(0, lmax_pol - m + 1)  # rows l = m..lmax_pol
        np.testing.assert_allclose(lo[:, 0], f[:, 0], rtol=0, atol=1e-13 * scale)
        np.testing.assert_allclose(lo[:n_p, 1:], f[:n_p, 1:], rtol=0, atol=1e-13 * scale)
        assert not lo[n_p:, 1:].any()


def test_bench_transfer_stokes_compares_both_paths_on_the_same_baselines():
    """`mmflow bench transfer --stokes IQUV` times both paths on the same baselines: full Stokes solves for
    4x the unknowns from 4x the correlations, so it cannot cost less than Stokes I; its flop count is
    40-52x the Stokes-I one (4 x 4^2 for the Gram; measured 45x at lmax 1000: docs/stokes.md)."""
    from mmflow.bench.stokes import compare

    r = compare(16, 4)
    assert (r["lmax"], r["stokes_lmax"], r["baselines"]) == (16, 16, 4)  # the default band limit: lmax if lower
    assert r["full_over_i"] > 1 and r["full_stokes_s_per_baseline"] == r["full_stokes_s"] / 4
    assert 30 < r["flops_full_over_i"] < 64
    # Q, U, V to l = 4: the herk of (L + 3 P)^2 and the spin-2 GEMMs shrink towards the four correlations'
    # Stokes-I work (4x the rows)
    low = compare(16, 4, lmax_p=4)
    assert low["stokes_lmax"] == 4 and 4 < low["flops_full_over_i"] < r["flops_full_over_i"] / 2
