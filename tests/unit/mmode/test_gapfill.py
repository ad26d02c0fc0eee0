"""Flagged sidereal bins: weighted least-squares m-modes against the unflagged transform.

Visibilities come from mmflow's independent time-domain simulator (a band-limited random
sky on a Gauss-Legendre grid exact for every baseline, so each drift scan is a trigonometric
polynomial of band limit ``min(lmax, M_b)``) for four OVRO-LWA core stands (5-12 m
baselines, ``M_b ~ 30``) and two stands of the paper-2017 array 106 m and 160 m out
(``M_b`` 75-160) at 40 MHz, ``mmax = 160``, ``N = 512`` bins.
"""
import numpy as np
import pytest

from mmflow.errors import InputError
from mmflow.mmode.gapfill import _from_layout, longest_gap, lsq_mmodes, relative_rms, unbridged_gaps, zero_filled_error
from mmflow.mmode.transfer import fringe_bandlimit
from mmflow.mmode.transform import bin_occupancy, mmode_transform, sidereal_bins

F_HZ, MMAX, N_BINS = 40e6, 160, 512
STANDS = ["LWA-112", "LWA-113", "LWA-114", "LWA-115", "LWA-161", "LWA-293"]


def _simulate(lsts, stands=STANDS):
    from mmflow.simulate.visibilities import gauss_legendre_points, simulate_drift_scan
    from mmflow.sky.diffuse import band_limited_random_alm
    from mmflow.telescope import Telescope, ovro_lwa_layout
    from mmflow.telescope.beams import GaussianBeam

    tel = Telescope(ovro_lwa_layout("paper-2017", stands=stands), GaussianBeam(30), [F_HZ])
    pairs = tel.antenna_pairs()
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    blen = np.linalg.norm(tel.baselines_enu(pairs), axis=1)
    lf = fringe_bandlimit(blen * F_HZ / 299792458.0, tel.beam.lmax_hint)
    sky = gauss_legendre_points(band_limited_random_alm(MMAX, seed=1), MMAX, MMAX + lf + 8)
    names = [(tel.layout.names[i], tel.layout.names[j]) for i, j in pairs]
    return tel.baseline_lmax(F_HZ, MMAX, pairs), names, blen, simulate_drift_scan(tel, F_HZ, lsts, sky, pairs)


@pytest.fixture(scope="module")
def drift():
    lst = 2 * np.pi * np.arange(N_BINS) / N_BINS
    band, names, blen, vis = _simulate(lst)
    ref = mmode_transform(vis, MMAX)
    # the premise: no power beyond each baseline's band limit
    m = np.arange(MMAX + 1)
    for b in range(len(names)):
        assert np.linalg.norm(ref[m > band[b], :, b]) < 1e-9 * np.linalg.norm(ref[:, :, b])
    return {"vis": vis, "band": band, "ref": ref, "blen": blen, "lst": lst, "names": names}


def _block_flags(rng, n, n_blocks=4, fraction=0.2):
    """``n_blocks`` disjoint runs of flagged bins, one at a random place in each ``n / n_blocks`` segment."""
    w = np.ones(n)
    seg, length = n // n_blocks, int(round(fraction * n / n_blocks))
    for k in range(n_blocks):
        s = k * seg + rng.integers(0, seg - length)
        w[s:s + length] = 0
    return w


def _undetermined_fraction(weights, band, truth_col, threshold):
    """Share of the true m-modes in directions the flagged data do not measure (independent, dense).

    Eigenvectors of ``A / c_0 = F^H W F / sum w`` (built explicitly from the phases) with
    eigenvalue below ``threshold``: no estimator from these bins can recover that part.
    """
    ms = np.arange(-band, band + 1)
    f = np.exp(1j * np.outer(2 * np.pi * np.arange(len(weights)) / len(weights), ms))
    ev, u = np.linalg.eigh(f.conj().T @ (weights[:, None] * f) / weights.sum())
    c = u.conj().T @ _from_layout(truth_col[:, :, None], band)[0]
    return np.sqrt(np.sum(np.abs(c[ev < threshold]) ** 2) / np.sum(np.abs(c) ** 2))


def test_random_flags_recovered_where_zero_filling_scatters_power(drift):
    """5 % of integrations flagged at random: nothing is lost, the fit is exact to the Tikhonov bias."""
    rng = np.random.default_rng(5)
    w = np.ones_like(drift["vis"].real)
    w[rng.random(N_BINS) < 0.05] = 0
    res = lsq_mmodes(drift["vis"], w, MMAX, drift["band"])
    assert res.converged.all() and res.iterations.max() < 40
    err = relative_rms(res.mmodes, drift["ref"])
    zf = zero_filled_error(drift["vis"], w, MMAX, drift["ref"])
    print("5% random: lsq", err.round(8), "zero-filled", zf.round(3))
    # measured: lsq 1.0e-6..2.0e-6 = the bias lambda / (1 - 0.05) of regularization=1e-6; zero-filled 0.19-0.22
    assert np.all(err < 5e-6)
    assert np.all(zf > 0.1)
    res0 = lsq_mmodes(drift["vis"], w, MMAX, drift["band"], regularization=0)
    assert np.all(relative_rms(res0.mmodes, drift["ref"]) < 1e-9)  # CG tolerance 1e-10


def test_block_flags_lose_only_what_the_data_do_not_measure(drift):
    """20 % of integrations in four blocks (~26 bins each).

    Short baselines (``M_b ~ 30``: a block spans ~3 Nyquist intervals ``N / (2 M_b + 1)``) are
    recovered; on the 106-160 m baselines a block spans ~8-16 of them and the part of the
    drift scan inside the gaps is not in the data. There the fit's error must equal the true
    m-modes' share in the unmeasured eigen-directions of the normal matrix (computed densely
    here, independently of the solver): the fit loses that and nothing else.
    """
    rng = np.random.default_rng(11)
    wcol = _block_flags(rng, N_BINS)
    assert abs(wcol.mean() - 0.8) < 0.01
    w = np.repeat(wcol[:, None], drift["vis"].shape[1], axis=1)
    res = lsq_mmodes(drift["vis"], w, MMAX, drift["band"])
    assert res.converged.all()
    err = relative_rms(res.mmodes, drift["ref"])
    zf = zero_filled_error(drift["vis"], w, MMAX, drift["ref"])
    print("20% blocks: M_b", drift["band"], "lsq", err.round(4), "zero-filled", zf.round(3))
    short = drift["band"] <= 40
    assert short.sum() == 6
    # measured: short 3.6e-4..1.8e-3 (lambda / smallest eigenvalue ~1e-3), zero-filled 0.41-0.53
    assert np.all(err[short] < 5e-3) and np.all(zf[short] > 0.3)
    assert np.all(err <= zf)
    for b in np.flatnonzero(~short)[np.unique(drift["band"][~short], return_index=True)[1]]:  # M_b 75, 123-160
        lost = _undetermined_fraction(wcol, drift["band"][b], drift["ref"][:, :, b], 1e-6)
        assert lost > 0.1  # the premise: these gaps hide signal from this baseline
        # measured: err / lost = 0.98-1.0
        assert err[b] <= 1.02 * lost + 2e-3 and err[b] >= 0.9 * lost


def test_prior_fills_what_the_data_leave_open(drift):
    """With a prior (e.g. a first-pass map's model m-modes) the gaps take the prior, the rest the data."""
    rng = np.random.default_rng(11)
    w = np.repeat(_block_flags(rng, N_BINS)[:, None], drift["vis"].shape[1], axis=1)
    ref = drift["ref"]
    exact = lsq_mmodes(drift["vis"], w, MMAX, drift["band"], prior=ref)
    assert np.all(relative_rms(exact.mmodes, ref) < 1e-6)
    noise = rng.normal(size=ref.shape) + 1j * rng.normal(size=ref.shape)
    noise *= (np.arange(MMAX + 1)[:, None] <= drift["band"][None, :])[:, None, :]
    noise[0, 1] = 0
    prior = ref + 0.3 * noise * np.sqrt(np.mean(np.abs(ref) ** 2, axis=(0, 1)))
    got = lsq_mmodes(drift["vis"], w, MMAX, drift["band"], prior=prior)
    prior_err = relative_rms(prior, ref)
    # the data correct every measured direction: what is left is the prior's error in the gaps
    err = relative_rms(got.mmodes, ref)
    print("prior error", prior_err.round(3), "after the fit", err.round(4))
    assert np.all(err < 0.6 * prior_err)
    assert np.all(err[drift["band"] <= 40] < 0.01 * prior_err[drift["band"] <= 40])


def test_equal_weights_reduce_to_the_plain_transform(drift):
    vis = drift["vis"]
    w = np.full(vis.shape, 3.0)
    ref = mmode_transform(vis, MMAX)
    res = lsq_mmodes(vis, w, MMAX, regularization=0)
    assert np.all(res.iterations == 1)
    assert np.abs(res.mmodes - ref).max() < 1e-12 * np.abs(ref).max()
    # the default Tikhonov term scales by 1 / (1 + lambda)
    res = lsq_mmodes(vis, w, MMAX)
    np.testing.assert_allclose(res.mmodes, ref / (1 + 1e-6), atol=1e-13 * np.abs(ref).max())
    assert np.all(res.n_filled == N_BINS) and np.allclose(res.weight_sum, 3.0 * N_BINS)


def test_offgrid_lsts_use_the_exact_phases(drift):
    """LSTs a third of a bin off the grid: equal to the plain transform's direct DFT and to the on-grid m-modes."""
    off = drift["lst"] + 0.37 * 2 * np.pi / N_BINS
    _, names, blen, vis = _simulate(off, ["LWA-112", "LWA-113", "LWA-293"])  # 5 m and two 160 m baselines
    assert blen.max() > 150
    binned, wsum, offset = sidereal_bins(off, vis, n_bins=N_BINS)
    dft = mmode_transform(binned, MMAX, offset)
    res = lsq_mmodes(binned, wsum, MMAX, regularization=0, offset=offset)
    scale = np.abs(dft).max()
    assert np.abs(res.mmodes - dft).max() < 1e-10 * scale  # NUFFT accuracy ~1e-12
    ref = drift["ref"][:, :, [drift["names"].index(nm) for nm in names]]
    assert np.abs(res.mmodes - ref).max() < 1e-9 * scale
    assert np.abs(lsq_mmodes(binned, wsum, MMAX, regularization=0).mmodes - ref).max() > 1e-3 * scale


def test_irregular_phases_and_flags_match_a_dense_least_squares_solve():
    """Random per-bin offsets (several days folded unevenly) and random weights: CG = numpy lstsq."""
    rng = np.random.default_rng(2)
    n, nbl, mmax = 300, 3, 60
    band = np.array([20, 45, 60])
    offset = rng.uniform(-0.5, 0.5, n) * 2 * np.pi / n
    phi = 2 * np.pi * np.arange(n) / n + offset
    w = rng.uniform(0.5, 2.0, (n, nbl)) * (rng.random((n, nbl)) > 0.1)
    vis = rng.normal(size=(n, nbl)) + 1j * rng.normal(size=(n, nbl))
    res = lsq_mmodes(vis, w, mmax, band, offset=offset, regularization=1e-3, tol=1e-12)
    for b in range(nbl):
        ms = np.arange(-band[b], band[b] + 1)
        f = np.exp(1j * np.outer(phi, ms))
        normal = f.conj().T @ (w[:, b, None] * f) + 1e-3 * w[:, b].sum() * np.eye(len(ms))
        x = np.linalg.solve(normal, f.conj().T @ (w[:, b] * vis[:, b]))
        got = _from_layout(res.mmodes[:, :, b:b + 1], band[b])[0]
        np.testing.assert_allclose(got, x, atol=1e-9 * np.abs(x).max())
        assert np.allclose(res.rss[b], np.sum(w[:, b] * np.abs(vis[:, b] - f @ x) ** 2), rtol=1e-9)
        assert np.all(res.mmodes[band[b] + 1:, :, b] == 0)
    assert np.array_equal(res.n_filled, (w > 0).sum(axis=0))


def test_empty_baseline_and_bad_input():
    n = 64
    vis = np.ones((n, 2), complex)
    w = np.ones((n, 2))
    w[:, 1] = 0
    res = lsq_mmodes(vis, w, 10)
    assert np.all(res.mmodes[:, :, 1] == 0) and res.n_filled[1] == 0 and np.all(np.isfinite(res.mmodes))
    assert abs(res.mmodes[0, 0, 0] - 1) < 1e-5
    with pytest.raises(InputError, match="n_bins"):
        lsq_mmodes(vis, w, 40)
    with pytest.raises(InputError, match="band_limit"):
        lsq_mmodes(vis, w, 10, band_limit=[5, -1])
    with pytest.raises(InputError, match="bin_weight"):
        lsq_mmodes(vis, -w, 10)


def test_even_odd_splits_estimate_the_same_mmodes(drift):
    """Jackknife halves with 5 % flags: each half's fit returns the unflagged m-modes (N/2 = 256 bins)."""
    from mmflow.mmode.gapfill import split_lsq_mmodes
    from mmflow.mmode.transform import split_mmode_transform

    keep = drift["band"] <= 100  # a half holds ~243 filled bins: enough for 2 M_b + 1 <= 201 unknowns
    vis, band = drift["vis"][:, keep], drift["band"][keep]
    w = np.ones(vis.shape)
    w[np.random.default_rng(8).random(N_BINS) < 0.05] = 0
    mm, res = split_lsq_mmodes(vis, w, MMAX, None, ("full", "even", "odd"), band, regularization=0)
    ref = drift["ref"][:, :, keep]
    for k in range(3):
        assert np.all(relative_rms(mm[k], ref) < 1e-8)
    # equal weights: the plain split transform (at mmax 100, which its halves can resolve)
    plain = split_mmode_transform(vis, 100, None, ("full", "even", "odd"))
    eq, _ = split_lsq_mmodes(vis, np.ones(vis.shape), 100, None, ("full", "even", "odd"), band, regularization=0)
    assert np.abs(eq - plain).max() < 1e-10 * np.abs(plain).max()  # the odd half goes through the NUFFT


@pytest.mark.parametrize("snr", [1e4, 100.0, 1.0])
def test_noisy_gaps_never_worse_than_zero_filling_when_the_noise_is_known(drift, snr):
    """20 % block flags with noise at a signal-to-noise ratio ``snr`` per bin.

    Given ``sigma^2`` (or estimating it from the residual), empty bins are pseudo-observations
    of the prior (0) with weight ``sigma^2 / S``: never worse than zero-filling, far better at
    high signal-to-noise where the data constrain the gaps. Without it, the long baselines'
    weakly measured directions amplify the noise.
    """
    rng = np.random.default_rng(int(snr) + 3)
    vis, band, ref = drift["vis"], drift["band"], drift["ref"]
    s2 = np.mean(np.abs(vis) ** 2, axis=0) / snr
    noisy = vis + np.sqrt(s2 / 2) * (rng.normal(size=vis.shape) + 1j * rng.normal(size=vis.shape))
    w = np.repeat(_block_flags(rng, N_BINS)[:, None], vis.shape[1], axis=1)
    zf = zero_filled_error(noisy, w, MMAX, ref)
    known = relative_rms(lsq_mmodes(noisy, w, MMAX, band, sigma2=s2).mmodes, ref)
    est = relative_rms(lsq_mmodes(noisy, w, MMAX, band, sigma2="residual").mmodes, ref)
    bare = relative_rms(lsq_mmodes(noisy, w, MMAX, band).mmodes, ref)
    print(f"snr {snr:g}: zero-filled {zf.round(3)}\n known sigma2 {known.round(3)}\n residual {est.round(3)}"
          f"\n no sigma2 {bare.round(2)}")
    assert np.all(known <= 1.02 * zf) and np.all(est <= 1.02 * zf)
    short = band <= 40
    if snr >= 1e4:  # measured: short 0.05-0.23 against 0.51-0.57 zero-filled
        assert np.all(known[short] < 0.5 * zf[short])
    if snr <= 100:
        assert np.any(bare[~short] > 2 * zf[~short])  # the hazard the noise weighting removes


def test_paper_scale_one_sidereal_day_at_mmax_1000():
    """N = 6628 bins (13 s), M_b = 1000: random band-limited scans, 5 % random and 20 % block flags."""
    rng = np.random.default_rng(21)
    n, band, nbl = 6628, 1000, 4
    ms = np.arange(-band, band + 1)
    x = rng.normal(size=(2 * band + 1, nbl)) + 1j * rng.normal(size=(2 * band + 1, nbl))
    grid = np.zeros((n, nbl), complex)
    grid[ms % n] = x
    vis = np.fft.ifft(grid, axis=0) * n
    ref = mmode_transform(vis, band)
    np.testing.assert_allclose(ref[:, 0], x[band:], atol=1e-10)
    eq = lsq_mmodes(vis, np.ones(vis.shape), band, regularization=0)
    assert np.abs(eq.mmodes - ref).max() < 1e-12 * np.abs(ref).max()
    w = np.where(rng.random((n, 1)) < 0.05, 0.0, 1.0) * np.ones((1, nbl))
    res = lsq_mmodes(vis, w, band)
    assert res.converged.all() and res.iterations.max() <= 20  # measured 15-17
    assert np.all(relative_rms(res.mmodes, ref) < 5e-6)
    s2 = np.mean(np.abs(vis) ** 2, axis=0) / 100
    noisy = vis + np.sqrt(s2 / 2) * (rng.normal(size=vis.shape) + 1j * rng.normal(size=vis.shape))
    wb = np.repeat(_block_flags(rng, n)[:, None], nbl, axis=1)
    blk = lsq_mmodes(noisy, wb, band, sigma2=s2)
    assert blk.converged.all() and blk.iterations.max() <= 60  # measured 41: the gap weights bound the conditioning
    assert np.all(relative_rms(blk.mmodes, ref) <= zero_filled_error(noisy, wb, band, ref))


def test_power_beyond_mmax_is_fitted_not_folded_in(drift):
    """Imaging at mmax 60 a sky with power to m = 160: fit each baseline's own band limit, keep m <= 60.

    Clipping the fit at mmax would fold the power at 60 < |m| <= M_b into the kept modes
    through the flags' spectrum (as zero-filling does).
    """
    rng = np.random.default_rng(13)
    w = np.ones(drift["vis"].shape)
    w[rng.random(N_BINS) < 0.05] = 0
    ref = drift["ref"][:61]
    full = lsq_mmodes(drift["vis"], w, 60, drift["band"])
    clipped = lsq_mmodes(drift["vis"], w, 60, np.minimum(drift["band"], 60))
    e_full, e_clip = relative_rms(full.mmodes, ref), relative_rms(clipped.mmodes, ref)
    print("band beyond mmax: fitted", e_full.max(), "clipped", e_clip.round(3))
    assert full.mmodes.shape == (61, 2, drift["vis"].shape[1]) and np.all(full.band_limit == drift["band"])
    assert np.all(e_full < 5e-6)
    beyond = np.linalg.norm(drift["ref"][61:], axis=(0, 1)) / np.linalg.norm(ref, axis=(0, 1))
    print("power beyond m = 60 (relative)", beyond.round(3))
    wide = beyond > 0.05  # measured: clipped errors 0.03-0.05 there
    assert wide.sum() >= 4 and np.all(e_clip[wide] > 0.01) and np.all(e_clip[wide] > 1e3 * e_full[wide])


def test_unbridged_gaps_against_nyquist_intervals():
    """A gap is bridged while it is shorter than ``N / (2 M_b + 1)`` bins, the band limit's sample spacing."""
    n = 60
    w = np.ones((n, 4))
    w[55:, 0] = w[:3, 0] = 0  # 8 bins across phi = 0
    w[10:14, 1] = 0  # 4 bins
    w[:, 2] = 0  # no data: dropped, not counted
    w[::7, 3] = 0  # single bins
    np.testing.assert_array_equal(longest_gap(w), [8, 4, n, 1])
    # M_b = 5: 60 / 11 = 5.45 bins per Nyquist interval; 3: 8.6, 8: 3.5, 30: 0.98
    np.testing.assert_array_equal(unbridged_gaps(w, 5), [True, False, False, False])
    np.testing.assert_array_equal(unbridged_gaps(w, [3, 8, 3, 30]), [False, True, False, True])


def test_bin_occupancy_is_the_binned_weight_of_sidereal_bins():
    """The driver's occupancy (no values summed) marks the bins ``sidereal_bins`` fills, over several days."""
    rng = np.random.default_rng(1)
    lst = np.sort(rng.uniform(0, 4 * np.pi, 900))
    good = rng.random((900, 30, 2)) > 0.3
    good[100:300] = False
    _, bin_weight, _ = sidereal_bins(lst, good.astype(complex), good.astype(float), 200, 0.0)
    np.testing.assert_array_equal(bin_occupancy(lst, good, 200), bin_weight > 0)
