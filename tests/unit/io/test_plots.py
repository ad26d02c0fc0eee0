"""Spectral-index figures: the three-colour Mollweide of nu^2.5-scaled channels and the beta / R^2
panels, checked on synthetic maps of known spectral index (pixel colours, not just a file)."""
import healpy
import numpy as np
import pytest

from mmflow.io.plots import mollweide_lonlat, mollweide_pixels, write_spectral_index_png, write_three_colour_png
from mmflow.io.report import png_size

FREQS = np.array([36.528e6, 52.224e6, 73.152e6])


def test_mollweide_grid_inverts_the_projection():
    from mmflow.io.plots import _project

    lon, lat = mollweide_lonlat(400)
    ok = np.isfinite(lon)
    assert 0.78 < ok.mean() < 0.79  # the ellipse fills pi / 4 of its box
    px, py = _project(lon[ok], lat[ok], 400)
    yy, xx = np.nonzero(ok)
    np.testing.assert_allclose(px, xx, atol=1e-6)
    np.testing.assert_allclose(py, yy, atol=1e-6)
    pix = mollweide_pixels(8, 400)
    assert set(np.unique(pix[pix >= 0])) == set(range(healpy.nside2npix(8)))  # every pixel drawn


def test_three_colour_white_where_index_is_minus_2p5(tmp_path):
    nside = 32
    x, y, z = healpy.pix2vec(nside, np.arange(healpy.nside2npix(nside)))
    t0 = 2000.0 * (1.5 + x)  # brightness structure
    beta = np.where(z > 0.3, -2.5, np.where(z < -0.3, -2.0, -3.0))  # north: white, south: flatter (blue)
    maps = [t0 * (f / FREQS[0]) ** beta for f in FREQS]
    mask = z > -0.9
    out = write_three_colour_png(tmp_path / "rgb.png", maps[::-1], FREQS[::-1], mask=mask, xsize=400)
    assert out["freqs_mhz"] == pytest.approx(FREQS / 1e6)  # red = lowest frequency whatever the order given
    img = out["rgb"]
    lon, lat = mollweide_lonlat(400)
    north = np.isfinite(lat) & (np.sin(lat) > 0.4)
    south = np.isfinite(lat) & (np.sin(lat) < -0.4) & (np.sin(lat) > -0.85)
    band = np.isfinite(lat) & (np.abs(np.sin(lat)) < 0.2)
    np.testing.assert_allclose(img[north][:, 0], img[north][:, 2], atol=1e-9)  # R = G = B: grey-white
    assert np.all(img[south][:, 2] > img[south][:, 0])  # flatter than -2.5: blue
    assert np.all(img[band][:, 0] > img[band][:, 2])  # steeper: red
    never = np.isfinite(lat) & (np.sin(lat) < -0.95)
    np.testing.assert_allclose(img[never], 0.5)  # unobserved: grey
    assert png_size((tmp_path / "rgb.png").read_bytes())[0] > 400


def test_spectral_index_panels_from_tt_maps(tmp_path):
    from mmflow.analysis.spectral_index import local_tt

    nside = 16
    np.random.seed(4)
    g = healpy.alm2map(healpy.synalm(np.r_[0, 0, (np.arange(2, 33) / 2.0) ** -2.0], lmax=32), nside, lmax=32)
    t1 = 4000.0 * np.exp(0.6 * g / g.std())
    x, y, z = healpy.pix2vec(nside, np.arange(healpy.nside2npix(nside)))
    truth = -2.5 + 0.1 * z
    tt = local_tt(t1, t1 * (FREQS[2] / FREQS[0]) ** truth + 300.0, FREQS[0], FREQS[2], radius_deg=15.0, nside_out=8)
    out = write_spectral_index_png(tmp_path / "beta.png", tt["beta"], tt["r2"], FREQS[0], FREQS[2], r2_min=0.9)
    assert out["beta_median"] == pytest.approx(np.median(-2.5 + 0.1 * healpy.pix2vec(8, np.arange(768))[2]), abs=0.02)
    assert out["r2_median"] > 0.9 and out["drawn_fraction"] > 0.9
    w, h = png_size((tmp_path / "beta.png").read_bytes())
    assert w > 2 * h
