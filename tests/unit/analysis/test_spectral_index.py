"""Jackknife noise and the science products (paper section 4, Table 1)."""
import healpy
import numpy as np
import pytest

from mmflow.imaging import jackknife, psf
from mmflow.imaging.clean import never_seen_dec_min, observed_mask
from mmflow.mmode.transform import mmode_transform
from mmflow.sky.diffuse import band_limited_random_alm

from tests.imaging_helpers import LMAX, Imager, to_time


def test_half_grids_measure_the_same_mmodes_with_the_half_bin_phase(blocks):
    n_bins = 4 * LMAX + 8
    v = to_time(blocks, band_limited_random_alm(LMAX, seed=1), n_bins)
    split = jackknife.split_mmodes(v, LMAX)
    scale = np.abs(split["all"]).max()
    for half in ("even", "odd"):
        np.testing.assert_allclose(split[half], split["all"], atol=1e-10 * scale)
    naive = mmode_transform(v[1::2], LMAX)  # the odd half as if it sat on the half grid: wrong
    assert np.abs(naive - split["all"]).max() > 0.1 * scale
    with pytest.raises(ValueError, match="cannot be halved"):
        jackknife.split_mmodes(v[:2 * LMAX], LMAX)


def test_jackknife_noise_matches_a_monte_carlo_of_the_map_noise(blocks, small_telescope):
    n_bins, sigma = 4 * LMAX + 8, 3.0
    eps = 1e-3 * max(np.linalg.eigvalsh(b.conj().T @ b)[-1] for b in blocks.values())
    imager = Imager(blocks, eps)
    mask = observed_mask(16, never_seen_dec_min(small_telescope.lat_rad))
    nb = blocks[0].shape[0]
    rng = np.random.default_rng(7)

    def noise():
        return sigma * (rng.normal(size=(n_bins, nb)) + 1j * rng.normal(size=(n_bins, nb))) / np.sqrt(2)

    mc = np.array([imager.map(mmode_transform(noise(), LMAX)) for _ in range(60)])
    var_mc = np.mean(np.var(mc, axis=0, ddof=1)[mask])
    signal = to_time(blocks, 50 * band_limited_random_alm(LMAX, seed=2), n_bins)  # a bright sky cancels
    jk = []
    for _ in range(20):
        sp = jackknife.split_mmodes(signal + noise(), LMAX)
        maps = {k: imager.map(v) for k, v in sp.items()}
        jk.append(jackknife.jackknife_variance(maps["all"], maps["even"], maps["odd"], mask))
    print("jackknife/MC sigma ratio", np.sqrt(np.mean(jk) / var_mc))
    assert np.sqrt(np.mean(jk)) == pytest.approx(np.sqrt(var_mc), rel=0.05)
    assert np.mean(np.var(mc, axis=0)[mask]) > 0


def test_noise_summary_units():
    out = jackknife.noise_summary(1000.0, 73.152e6, psf.gaussian_solid_angle(np.deg2rad(16.8 / 60),
                                                                             np.deg2rad(14.6 / 60)))
    from mmflow.sky.units import jy_per_sr_per_kelvin

    assert out["kelvin"] == pytest.approx(1000.0 / jy_per_sr_per_kelvin(73.152e6))
    omega = np.pi / (4 * np.log(2)) * np.deg2rad(16.8 / 60) * np.deg2rad(14.6 / 60)
    assert out["mjy_per_beam"] == pytest.approx(1e6 * omega)
    table = {"dec": np.deg2rad([0.0, 90.0]), "major": np.deg2rad([16.8, 16.8]) / 60,
             "minor": np.deg2rad([14.6, 14.6]) / 60, "pa": np.zeros(2)}
    a = np.zeros(100)
    got = jackknife.jackknife_noise(a, a + 2000.0, a - 2000.0, None, 73.152e6, table)
    assert got["jy_per_sr"] == pytest.approx(2000.0) and got["beam_solid_angle_sr"] == pytest.approx(omega)


# ----------------------------------------------------------------------------- science products

def test_tt_recovers_an_injected_spectral_index_and_ignores_offsets():
    from mmflow.analysis.spectral_index import local_tt

    nside, nu1, nu2 = 32, 36.528e6, 73.152e6
    np.random.seed(3)
    g = healpy.alm2map(healpy.synalm(np.r_[0, 0, (np.arange(2, 65) / 2.0) ** -2.0], lmax=64), nside, lmax=64)
    t1 = 4000.0 * np.exp(0.6 * g / g.std())  # structure with dynamic range everywhere
    x, y, z = healpy.pix2vec(nside, np.arange(healpy.nside2npix(nside)))
    beta = -2.5 + 0.08 * z + 0.05 * x  # a smooth index map (-2.59 .. -2.41)
    t2 = t1 * (nu2 / nu1) ** beta
    out = local_tt(t1, t2, nu1, nu2, radius_deg=10.0, nside_out=8)
    xo, yo, zo = healpy.pix2vec(8, np.arange(healpy.nside2npix(8)))
    truth = -2.5 + 0.08 * zo + 0.05 * xo
    assert np.all(np.isfinite(out["beta"]))
    assert np.max(np.abs(out["beta"] - truth)) < 0.02
    assert np.median(out["r2"]) > 0.95
    off = local_tt(t1 + 300.0, t2 - 1234.0, nu1, nu2, radius_deg=10.0, nside_out=8)
    np.testing.assert_allclose(off["beta"], out["beta"], atol=1e-9)


def test_tt_regression_of_every_disc_equals_a_brute_force_one():
    """Each output pixel's slope and R^2 equal the weighted regression written out over every input
    pixel within the radius (angles from the dot products of all pixel pairs), masked pixels left
    out, discs with too few pixels NaN."""
    from mmflow.analysis.spectral_index import local_tt

    nside, nside_out, radius, nu1, nu2 = 16, 4, np.deg2rad(20.0), 40e6, 80e6
    rng = np.random.default_rng(5)
    npix = healpy.nside2npix(nside)
    t1 = 3000.0 + 500.0 * rng.normal(size=npix)
    t2 = 0.2 * t1 + 40.0 * rng.normal(size=npix) - 7.0
    vec = np.array(healpy.pix2vec(nside, np.arange(npix))).T
    mask = vec[:, 2] > -0.3  # a horizon: southern discs are partial or empty
    out = local_tt(t1, t2, nu1, nu2, radius_deg=20.0, nside_out=nside_out, mask=mask, min_pixels=25)
    centres = np.array(healpy.pix2vec(nside_out, np.arange(healpy.nside2npix(nside_out)))).T
    for q, c in enumerate(centres):
        ang = np.arccos(np.clip(vec @ c, -1, 1))
        inside = (ang <= radius) & mask
        if inside.sum() < 25:
            assert np.isnan(out["slope"][q]) and np.isnan(out["beta"][q])
            continue
        w = (1 - (ang[inside] / radius) ** 2) ** 2
        w /= w.sum()
        a, b = t1[inside], t2[inside]
        ma, mb = w @ a, w @ b
        v1, v2, cv = w @ (a - ma) ** 2, w @ (b - mb) ** 2, w @ ((a - ma) * (b - mb))
        assert out["slope"][q] == pytest.approx(cv / v1, rel=1e-10)
        assert out["r2"][q] == pytest.approx(cv ** 2 / (v1 * v2), rel=1e-10)
        assert out["beta"][q] == pytest.approx(np.log(cv / v1) / np.log(2.0), rel=1e-10)
    assert np.isfinite(out["slope"]).sum() > 100 and np.isnan(out["slope"]).sum() > 10


def test_flux_from_disc_minus_annulus_over_the_psf_sum():
    from mmflow.analysis.fluxscale import source_flux

    nside = 128
    v = healpy.ang2vec(np.deg2rad(50.0), 1.0)
    pix_v = np.array(healpy.pix2vec(nside, np.arange(healpy.nside2npix(nside)))).T
    d = np.arccos(np.clip(pix_v @ v, -1, 1))
    # a PSF with a negative bowl around its main lobe (like a filtered m-mode PSF)
    psf_map = 900.0 * np.exp(-0.5 * (d / np.deg2rad(0.8)) ** 2) - 40.0 * np.exp(-0.5 * (d / np.deg2rad(4.0)) ** 2)
    sky = 37.0 * psf_map + 250.0 + 3.0 * pix_v[:, 2]  # background: offset and a gradient
    got = source_flux(sky, psf_map, v, np.deg2rad(2.5), (np.deg2rad(3.0), np.deg2rad(4.5)))
    assert got == pytest.approx(37.0, rel=0.01)


def test_table1_formats_and_fraction_of_modes():
    from mmflow.analysis import table1
    from mmflow.imaging.jackknife import noise_summary

    ev = [np.array([1.0, 1e-3, 5.0]), np.array([2e-2, 3.0])]
    assert table1.fraction_of_modes(ev, 1e-2) == pytest.approx(4 / 5)
    tab = {"dec": np.deg2rad([-30.0, 90.0]), "major": np.deg2rad([20.0, 14.0]) / 60,
           "minor": np.deg2rad([16.0, 14.0]) / 60, "pa": np.zeros(2), "peak": np.ones(2)}
    noise = noise_summary(3e4, 73.152e6, 1e-5)
    rows = [table1.table1_row(73.152e6, 24e3, tab, noise, 0.512)]
    md = table1.to_markdown(rows)
    assert "73.152" in md and "0.512" in md and "18.5' x 15.5'" in md  # linear in dec: 20 - 6 * 30 / 120
    import csv
    import io
    import json

    back = list(csv.DictReader(io.StringIO(table1.to_csv(rows))))[0]
    assert float(back["fwhm_major_arcmin_dec+45"]) == pytest.approx(20 - 6 * 75 / 120)
    assert json.loads(table1.to_json(rows))[0]["noise_k"] == pytest.approx(noise["kelvin"])


def test_three_colour_is_white_for_index_minus_2p5():
    from mmflow.analysis.spectral_index import three_colour

    freqs = np.array([36.528e6, 52.224e6, 73.152e6])
    t = np.geomspace(100.0, 1e4, 50)
    rgb = three_colour([t * (f / freqs[0]) ** -2.5 for f in freqs], freqs)
    np.testing.assert_allclose(rgb[:, 0], rgb[:, 2], atol=1e-12)
    assert rgb.min() >= 0 and rgb.max() == pytest.approx(1.0)
    flat = three_colour([t * (f / freqs[0]) ** -2.0 for f in freqs], freqs)
    assert np.all(flat[:, 2] >= flat[:, 0])  # flatter spectrum: bluer
