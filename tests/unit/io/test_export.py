"""Maps a person can read: the never-seen sky masked (UNSEEN / grey), a stated colour scale,
a caption, and an L-curve that marks the chosen eps and the corner."""
import healpy
import numpy as np
import pytest

from mmflow.imaging.lcurve import default_eps_grid, lcurve_block, lcurve_corner
from mmflow.imaging.sky_mask import observed_declination_range, observed_sky_mask
from mmflow.io.export import write_healpix_fits, write_lcurve_png, write_mollweide_png
from mmflow.sky.frames import rotation_matrix

OVRO_LAT = 37.23977727
EPOCH = 2457802.0


@pytest.mark.parametrize("lat, h_min", [(OVRO_LAT, 0.0), (-30.7, 0.0), (OVRO_LAT, 20.0), (0.0, 0.0), (89.0, 5.0)])
def test_mask_is_the_sky_that_rises_above_the_horizon_in_a_day(lat, h_min):
    """Independent check: the highest elevation over a sampled sidereal day, from
    sin(el) = sin(lat) sin(dec) + cos(lat) cos(dec) cos(H)."""
    nside = 32
    mask = observed_sky_mask(nside, lat, min_elevation_deg=h_min)
    theta, _ = healpy.pix2ang(nside, np.arange(12 * nside**2))
    dec = np.pi / 2 - theta
    hour = np.linspace(0, 2 * np.pi, 721)[:, None]
    la = np.deg2rad(lat)
    el = np.rad2deg(np.arcsin(np.sin(la) * np.sin(dec) + np.cos(la) * np.cos(dec) * np.cos(hour))).max(axis=0)
    clear = np.abs(el - h_min) > 0.5  # pixels that do not graze the horizon
    assert np.array_equal(mask[clear], (el > h_min)[clear])
    lo, hi = observed_declination_range(lat, h_min)
    cap = (1 - np.sin(np.deg2rad(-lo))) / 2 if lo > -90 else 0.0  # area of dec < lo
    cap += (1 - np.sin(np.deg2rad(hi))) / 2 if hi < 90 else 0.0
    assert abs((1 - mask.mean()) - cap) < 0.01


def test_mask_in_galactic_frame_hides_the_south_celestial_pole():
    nside = 32
    to_date = rotation_matrix("galactic", "date", EPOCH)
    mask = observed_sky_mask(nside, OVRO_LAT, to_date)
    scp_gal = rotation_matrix("date", "galactic", EPOCH) @ np.array([0.0, 0.0, -1.0])
    ncp_gal = -scp_gal
    assert not mask[healpy.vec2pix(nside, *scp_gal)] and mask[healpy.vec2pix(nside, *ncp_gal)]
    l, b = healpy.vec2ang(scp_gal, lonlat=True)
    assert abs(l[0] - 302.9) < 0.5 and abs(b[0] + 27.1) < 0.5  # the SCP in Galactic coordinates
    # a rotation does not change the masked area: same fraction as in the frame of date
    assert abs(mask.mean() - observed_sky_mask(nside, OVRO_LAT).mean()) < 0.005


def test_fits_marks_the_never_seen_sky_unseen(tmp_path):
    nside = 16
    hmap = np.random.default_rng(1).normal(size=12 * nside**2)
    mask = observed_sky_mask(nside, OVRO_LAT)
    path = tmp_path / "m.fits"
    write_healpix_fits(path, hmap, {"FREQ": 40e6, "LMAX": 24, "BUNIT": "K", "COORDSYS": "C"}, mask=mask)
    back, header = healpy.read_map(str(path), h=True)
    header = dict(header)
    assert np.array_equal(back == healpy.UNSEEN, ~mask)
    np.testing.assert_array_equal(back[mask], hmap[mask])
    assert header["LMAX"] == 24 and header["FREQ"] == 40e6


def _grey_pixels(path):
    import matplotlib.image

    img = matplotlib.image.imread(str(path))[..., :3]
    return int(np.sum(np.all(np.abs(img - 0.6) < 0.01, axis=-1)))


def test_png_greys_exactly_the_masked_area_and_states_its_scale(tmp_path):
    """Mollweide is equal-area: the grey share of the disc is the masked share of the sky."""
    nside = 16
    rng = np.random.default_rng(2)
    hmap = rng.normal(size=12 * nside**2) + 100 * (rng.random(12 * nside**2) < 0.02)  # faint sky + bright spots
    mask = observed_sky_mask(nside, OVRO_LAT)
    kw = dict(title="test", unit="K", lmax=24, eps=0.01, freq_hz=40e6, frame="icrs", xsize=400)
    info = write_mollweide_png(tmp_path / "part.png", hmap, mask=mask, **kw)
    write_mollweide_png(tmp_path / "all.png", hmap, mask=np.zeros_like(mask), **kw)
    none = write_mollweide_png(tmp_path / "none.png", hmap, **kw)
    grey_part, grey_all = _grey_pixels(tmp_path / "part.png"), _grey_pixels(tmp_path / "all.png")
    assert grey_all > 10000 and _grey_pixels(tmp_path / "none.png") < 0.002 * grey_all  # (graticule lines)
    assert abs(grey_part / grey_all - info["masked_fraction"]) < 0.02
    assert abs(info["masked_fraction"] - (1 - np.sin(np.deg2rad(90 - OVRO_LAT))) / 2) < 0.01
    assert info["colorbar_label"].startswith("K; symmetric log scale, linear within +-")
    assert info["linthresh"] < 10 < info["vmax"]  # the faint sky is in the linear part, the spots beyond
    for words in ("40.000 MHz", "lmax 24", "eps 0.01", "resolution 7.5 deg", "grey: sky never above"):
        assert words in info["caption"]
    assert "grey" not in none["caption"]


def test_lcurve_marks_chosen_and_corner_and_returns_their_ratio(tmp_path):
    rng = np.random.default_rng(0)
    n = 60
    b = rng.normal(size=(200, n)) * np.logspace(0, -4, n)
    v = b @ rng.normal(size=n) + 0.01 * rng.normal(size=200)
    eps = default_eps_grid()
    sol, res = lcurve_block(b.T @ b, b.T @ v, v @ v, eps)
    lc = np.stack([sol, res], axis=1)
    corner = lcurve_corner(sol, res, eps)
    ratio = write_lcurve_png(tmp_path / "lc.png", lc, eps, 0.01, freq_hz=40e6, weighted=True)
    assert ratio == pytest.approx(0.01 / corner) and (tmp_path / "lc.png").stat().st_size > 10000
    assert write_lcurve_png(tmp_path / "lc2.png", lc, eps, 0.01, corner=0.001) == pytest.approx(10.0)
