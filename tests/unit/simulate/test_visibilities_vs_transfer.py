"""v = B a agrees with the independent time-domain simulator after the m-mode transform."""
import numpy as np
import pytest

from mmflow.conventions import m_slice
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit, iter_transfer_blocks, make_grid
from mmflow.mmode.transform import block_vector, mmode_transform, sidereal_bins
from mmflow.simulate.visibilities import SkyPoints, gauss_legendre_points, healpix_points, simulate_drift_scan
from mmflow.sky.diffuse import band_limited_random_alm


def test_band_limited_sky_matches_independent_simulation(small_telescope):
    tel, f, lmax = small_telescope, 40e6, 40
    pairs = tel.antenna_pairs()
    b = baselines_in_wavelengths(tel, pairs, f)
    lf = fringe_bandlimit(np.linalg.norm(b, axis=1), tel.beam.lmax_hint)
    alm = band_limited_random_alm(lmax, seed=1)
    sky = gauss_legendre_points(alm, lmax, lmax + lf + 8)
    n = 2 * lmax + 2
    lst = 2 * np.pi * np.arange(n) / n
    vis = simulate_drift_scan(tel, f, lst, sky, pairs)
    mm = mmode_transform(sidereal_bins(lst, vis, n_bins=n)[0], lmax)
    err = nrm = 0.0
    for m, blk in iter_transfer_blocks(make_grid(tel.lat_rad, tel.beam, f, lmax, lf), b):
        v = block_vector(mm, m)
        err += np.sum(np.abs(v - blk @ alm[m_slice(lmax, m)]) ** 2)
        nrm += np.sum(np.abs(v) ** 2)
    assert np.sqrt(err / nrm) < 1e-3
    assert np.sqrt(err / nrm) < 1e-9  # in fact exact to rounding with a smooth beam


def test_any_starting_lst_and_several_days_fold_to_same_mmodes(small_telescope):
    tel, f = small_telescope, 40e6
    sky = SkyPoints(np.array([[0.5, 0.5, np.sqrt(0.5)]]), np.array([50.0]))
    n = 48
    base = 2 * np.pi * np.arange(n) / n
    ref = mmode_transform(sidereal_bins(base, simulate_drift_scan(tel, f, base, sky), n_bins=n)[0], 20)
    shifted = np.concatenate([base + 2 * np.pi * 17 / n, base + 2 * np.pi * 17 / n + 2 * np.pi])  # 2 days
    vis = simulate_drift_scan(tel, f, shifted, sky)
    got = mmode_transform(sidereal_bins(shifted, vis, n_bins=n)[0], 20)
    np.testing.assert_allclose(got, ref, atol=1e-12)


def test_healpix_and_point_inputs_agree_for_a_single_pixel(small_telescope):
    import healpy

    tel = small_telescope
    nside = 8
    hmap = np.zeros(healpy.nside2npix(nside))
    hmap[100] = 3.0
    vec = np.array(healpy.pix2vec(nside, 100))
    lst = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    a = simulate_drift_scan(tel, 40e6, lst, healpix_points(hmap))
    b = simulate_drift_scan(tel, 40e6, lst, SkyPoints(vec[None], np.array([3.0 * 4 * np.pi / len(hmap)])))
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_lsts_off_the_bin_grid_keep_their_exact_phase(small_telescope):
    """A drift scan starting at an arbitrary LST: the transform uses the true sample LSTs."""
    tel, f = small_telescope, 40e6
    sky = SkyPoints(np.array([[0.5, 0.5, np.sqrt(0.5)]]), np.array([50.0]))
    n = 160  # more bins than the band limit of V(phi): no aliasing in either transform
    base = 2 * np.pi * np.arange(n) / n
    ref = mmode_transform(sidereal_bins(base, simulate_drift_scan(tel, f, base, sky), n_bins=n)[0], 20)
    off = base + 0.37 * 2 * np.pi / n  # a third of a bin off the grid
    binned, _, offset = sidereal_bins(off, simulate_drift_scan(tel, f, off, sky), n_bins=n)
    assert np.allclose(offset, 0.37 * 2 * np.pi / n)
    np.testing.assert_allclose(mmode_transform(binned, 20, offset), ref, atol=1e-10)  # |V| ~ 5
    naive = mmode_transform(binned, 20)
    assert np.abs(naive - ref).max() > 1e-3 * np.abs(ref).max()  # snapping to bin centres is wrong


@pytest.mark.parametrize("path", ["every pair", "pair-wise", "few points"])
def test_blocked_threaded_simulator_matches_direct_sum(small_telescope, path, monkeypatch):
    """Pixel blocks, time threads, reversed pairs and signed fluxes against the sum of eq. 1, through
    the rank-k product of every pair, through the pair-wise product of a few baselines and through
    the per-baseline sum of a few points (a calibration model's sky); ``out`` filled in place."""
    from mmflow.conventions import enu_to_equatorial_matrix
    from mmflow.simulate import visibilities

    n_points = 3 * visibilities.PIXEL_BLOCK + 17
    if path == "pair-wise":
        monkeypatch.setattr(visibilities, "_simulate_block", visibilities._simulate_pairs)
    elif path == "few points":
        n_points = visibilities.FEW_POINTS  # the default choice for so few: no patch needed
        monkeypatch.setattr(visibilities, "few_pairs", lambda pairs, n: False)
        monkeypatch.setattr(visibilities, "_simulate_block", None)  # must not be reached
    else:
        monkeypatch.setattr(visibilities, "_simulate_pairs", visibilities._simulate_block)
    tel, f = small_telescope, 40e6
    rng = np.random.default_rng(3)
    vec = rng.normal(size=(n_points, 3))
    vec /= np.linalg.norm(vec, axis=1)[:, None]
    pairs = np.array([[0, 1], [2, 0], [1, 1], [3, 2]])
    x = tel.layout.enu * f / 299792458.0
    lst = np.array([0.3, 2.0, 4.1])
    for flux in (rng.uniform(0, 5, len(vec)), rng.normal(size=len(vec))):  # syrk path, signed path
        got = simulate_drift_scan(tel, f, lst, SkyPoints(vec, flux), pairs, threads=2)
        for t, phi in enumerate(lst):
            enu = vec @ enu_to_equatorial_matrix(tel.lat_rad, phi)
            w = np.where(enu[:, 2] > 0, tel.beam.power_enu(enu, f) * flux, 0.0)
            ref = [np.sum(w * np.exp(2j * np.pi * enu @ (x[j] - x[i]))) for i, j in pairs]
            np.testing.assert_allclose(got[t], ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())
        single = np.empty((len(lst), len(pairs)), np.complex64)
        assert simulate_drift_scan(tel, f, lst, SkyPoints(vec, flux), pairs, dtype=np.complex64, threads=1,
                                   out=single) is single
        np.testing.assert_allclose(single, got, atol=2e-5 * np.abs(got).max())


def test_an_empty_sky_simulates_zero_visibilities(small_telescope):
    """No sources and no diffuse sky (a noise-only simulation): zeros, not a crash (an empty pixel
    block once made the block loop's step 0)."""
    empty = SkyPoints(np.zeros((0, 3)), np.zeros(0))
    one = SkyPoints(np.array([[0.0, 0.0, 1.0]]), np.array([3.0]))
    lsts = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    v0 = simulate_drift_scan(small_telescope, 50e6, lsts, empty)
    v1 = simulate_drift_scan(small_telescope, 50e6, lsts, one)
    assert v0.shape == v1.shape and np.all(v0 == 0) and np.abs(v1).max() > 0


def test_a_corner_turn_chunk_of_a_large_array_is_computed_pair_wise():
    """The m-mode stage's chunk of 256 baselines at 256 antennas (one or two first antennas) is summed
    pair-wise; a time chunk of every baseline is one rank-k product."""
    from mmflow.simulate.visibilities import few_pairs

    n = 256
    pairs = np.array([(i, j) for i in range(n) for j in range(i, n)])
    assert few_pairs(pairs[1000:1256], n)
    assert not few_pairs(pairs, n)
    assert not few_pairs(pairs[:n * 32], n)  # 32 first antennas x every second one: the rank-k product
