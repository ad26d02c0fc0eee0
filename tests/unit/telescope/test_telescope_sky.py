"""Layouts, beams, sources, units and frames."""
import numpy as np
import pytest

from mmflow.errors import CoverageError, InputError
from mmflow.sky import units
from mmflow.sky.frames import rotate_alm, rotation_matrix
from mmflow.sky.sources import CATALOG, PAPER_REMOVED, SH12_CALIBRATORS, get_sources
from mmflow.telescope import Telescope, load_layout, ovro_lwa_layout
from mmflow.telescope.beam_factory import make_beam
from mmflow.telescope.beams import GaussianBeam, PyUVDataBeam, SinElevationBeam, ZernikeBeam


def test_ovro_presets_from_real_positions():
    full, core = ovro_lwa_layout("full"), ovro_lwa_layout("core")
    assert full.n_ant == 352 and core.n_ant == 251
    r = np.hypot(core.enu[:, 0], core.enu[:, 1])
    assert r.max() < 160 and np.hypot(full.enu[:, 0], full.enu[:, 1]).max() > 1400
    assert ovro_lwa_layout("leda512-2013").n_ant == 256
    assert ovro_lwa_layout("core", stands=["LWA-001", "LWA-002"]).n_ant == 2
    assert "d99cf6bb535f" in core.provenance
    tel = Telescope(core.select(np.arange(4)), SinElevationBeam(), [50e6])
    assert len(tel.antenna_pairs()) == 10  # with autos


def test_layout_file_with_missing_columns_names_line_and_fix(tmp_path):
    p = tmp_path / "ants.txt"
    p.write_text("# name e n u\nA1 0 0 0\nA2 5\n")
    with pytest.raises(InputError, match=r"ants.txt:3.*east/north.*Fix"):
        load_layout(p, 37.0, -118.0)


def test_lmax_too_small_warns_with_estimate():
    tel = Telescope(ovro_lwa_layout("core"), SinElevationBeam(), [73e6])
    with pytest.warns(UserWarning, match=r"raise lmax to ~\d+"):
        need = tel.check_lmax(100)
    assert need > 300


def test_zernike_beam_unity_at_zenith_symmetric_and_fits_an_analytic_beam():
    ref = SinElevationBeam(1.6)
    zb = ZernikeBeam.fit(ref, [40e6, 70e6])
    assert zb.power(0.0, 0.0, 50e6) == pytest.approx(1.0)
    za = np.deg2rad(40)
    vals = [zb.power(az, za, 50e6) for az in np.deg2rad([10, 100, 190, 280, 350])]  # 90-deg rotations and flips
    assert np.ptp(vals[:4]) < 1e-12 and vals[4] == pytest.approx(zb.power(np.deg2rad(10), za, 50e6))
    grid = np.deg2rad(np.linspace(0, 85, 30))
    assert np.max(np.abs(zb.power(0 * grid, grid, 50e6) - ref.power(0 * grid, grid, 50e6))) < 0.02
    assert zb.power(0.0, np.deg2rad(95), 50e6) == 0.0
    with pytest.raises(InputError, match="outside the model"):
        zb.power(0.0, 0.0, 80e6)


def test_pyuvdata_gaussian_beam_matches_ours():

    sigma = np.deg2rad(20.0)
    ours = GaussianBeam(fwhm_deg=np.rad2deg(sigma) * np.sqrt(8 * np.log(2)))
    theirs = make_beam({"type": "pyuvdata", "class": "GaussianBeam", "params": {"sigma": sigma, "sigma_type": "power"}})
    assert isinstance(theirs, PyUVDataBeam)
    az, za = np.deg2rad([0, 45, 200]), np.deg2rad([0, 30, 60])
    np.testing.assert_allclose(theirs.power(az, za, 50e6), ours.power(az, za, 50e6), rtol=1e-6)


def test_source_spectra_and_catalogue():
    assert set(PAPER_REMOVED) <= set(CATALOG) and set(SH12_CALIBRATORS) <= set(CATALOG)
    cyg = CATALOG["Cyg A"].flux(74e6)
    assert 14000 < cyg < 19000  # ~15-17 kJy at 74 MHz (paper section 3.5; Baars 1977)
    cas = CATALOG["Cas A"]
    assert cas.flux(74e6, 2017.0) / cas.flux(74e6, 1965.0) == pytest.approx(0.9923 ** 52, rel=1e-9)
    assert CATALOG["3C 286"].flux(150e6) == pytest.approx(27.477)
    with pytest.raises(InputError, match="unknown source"):
        get_sources(["Cyg B"])


def test_kelvin_jansky_round_trip():
    t = np.array([1.0, 1e4])
    np.testing.assert_allclose(units.jy_per_sr_to_kelvin(units.kelvin_to_jy_per_sr(t, 50e6), 50e6), t)
    # 1 K at 50 MHz: 2 k nu^2 / c^2 = 7.68e-25 W/m^2/Hz/sr = 76.8 Jy/sr
    assert units.jy_per_sr_per_kelvin(50e6) == pytest.approx(76.82, rel=1e-3)


def test_frame_rotation_moves_a_point_source_to_its_icrs_position():
    import healpy

    from mmflow.sky.diffuse import alm_to_map, point_source_alm

    epoch = 2457802.0  # 2017-02-18
    r = rotation_matrix("icrs", "date", epoch)
    cyg = CATALOG["Cyg A"].vector_icrs()
    # precession 2000 -> 2017 moves the pole by ~0.1 deg
    assert 0.05 < np.rad2deg(np.arccos(r[2, 2])) < 0.15
    lmax = 96
    alm_date = point_source_alm(r @ cyg, 1.0, lmax)
    hmap = alm_to_map(rotate_alm(alm_date, rotation_matrix("date", "icrs", epoch), lmax), 256, lmax)
    got = np.array(healpy.pix2vec(256, int(np.argmax(hmap))))
    assert np.rad2deg(np.arccos(got @ cyg)) < 0.3  # one pixel at nside 256 is 0.23 deg


def test_coverage_and_nan_errors():
    from mmflow.mmode.transform import sidereal_bins

    lst = np.linspace(0, np.pi, 50)
    with pytest.raises(CoverageError, match="sidereal bins hold data"):
        sidereal_bins(lst, np.ones((50, 3)), n_bins=64)
    vis = np.ones((64, 3), complex)
    vis[5, 1] = np.nan
    lst = 2 * np.pi * np.arange(64) / 64
    with pytest.raises(InputError, match="NaN/inf"):
        sidereal_bins(lst, vis, n_bins=64)
    w = np.ones((64, 3))
    w[5, 1] = 0
    binned, wsum, _ = sidereal_bins(lst, vis, weights=w, n_bins=64)  # flagged NaN is fine
    assert wsum[5, 1] == 0 and binned[5, 1] == 0


def test_gaussian_components_conserve_flux_and_centroid_and_match_analytic_visibility():
    from mmflow.sky.sources import Source, Spectrum

    src = Source("double", 120.0, 40.0, Spectrum("power_law", (100.0, 74e6, 0.0)),
                 components=[{"fraction": 0.6, "fwhm_major_arcmin": 30.0, "fwhm_minor_arcmin": 20.0, "pa_deg": 30.0},
                             {"fraction": 0.4, "dra_arcmin": 0.0, "ddec_arcmin": 0.0, "fwhm_major_arcmin": 30.0}])
    vec, flux = src.points(74e6)
    assert flux.sum() == pytest.approx(100.0)
    c = (vec * flux[:, None]).sum(0)
    assert np.rad2deg(np.arccos(c @ src.vector_icrs() / np.linalg.norm(c))) < 1e-3
    # a circular Gaussian of FWHM theta seen by a baseline b (wavelengths) perpendicular to the
    # line of sight: |V| = S exp(-2 pi^2 sigma^2 |b|^2)
    circ = Source("g", 0.0, 0.0, Spectrum("power_law", (1.0, 74e6, 0.0)), components=[{"fwhm_major_arcmin": 60.0}])
    vec, flux = circ.points(74e6, n_grid=21, n_sigma=5)
    sigma = np.deg2rad(1.0) / np.sqrt(8 * np.log(2))
    b = np.array([0.0, 40.0, 0.0])  # along +y, perpendicular to the source direction (+x)
    vis = np.sum(flux * np.exp(2j * np.pi * vec @ b))
    assert abs(vis) == pytest.approx(np.exp(-2 * np.pi**2 * sigma**2 * 40.0**2), rel=1e-3)


def test_telescope_location_is_an_earth_location():
    tel = Telescope(ovro_lwa_layout("core", radius_m=10), SinElevationBeam(), [50e6])
    assert tel.location.lat.deg == pytest.approx(37.23977727)


def test_apparent_sidereal_time_is_pyuvdatas_lst_and_utc_at_lsts_inverts_it():
    """mmflow's LAST (ERFA's GAST 2006/2000A + s' + longitude, without importing pyuvdata in every
    worker) equals pyuvdata's ``get_lst_for_time`` to rounding at three sites from 1968 to 2040,
    beyond both ends of the IERS table included; and the UTC that ``utc_at_lsts`` finds for a day of
    LSTs has, by pyuvdata's LST, those LSTs."""
    from pyuvdata.utils import get_lst_for_time

    from mmflow.simulate.corrupt import utc_at_lsts
    from mmflow.sky.frames import apparent_sidereal_time

    rng = np.random.default_rng(3)
    for jd0 in (2440000.5, 2451545.0, 2457802.0, 2462502.5, 2466000.5):  # 1968, 2000, 2017, 2030, 2040
        jd = jd0 + rng.uniform(0, 2, 300)
        for lat, lon, h in ((37.2398, -118.2817, 1183.0), (-30.72, 21.43, 1050.0), (0.0, 179.9, 0.0)):
            ours = apparent_sidereal_time(jd, lon)
            assert np.all((ours >= 0) & (ours < 2 * np.pi))
            theirs = get_lst_for_time(jd, latitude=lat, longitude=lon, altitude=h)
            assert np.abs(np.angle(np.exp(1j * (ours - theirs)))).max() < 1e-14
    layout = ovro_lwa_layout("core", radius_m=15)
    lsts = np.mod(1.0 + 2 * np.pi * np.arange(500) / 500, 2 * np.pi)  # wraps through 0
    t = utc_at_lsts(lsts, layout, 2460000.5)
    assert np.all(np.diff(t) > 0) and abs(t[0] - 2460000.5) < 1.0
    got = get_lst_for_time(t, latitude=layout.lat_deg, longitude=layout.lon_deg, altitude=layout.height_m)
    # to the resolution of a float64 Julian date (5e-10 d = 3.4e-9 rad of LST)
    assert np.abs(np.angle(np.exp(1j * (got - lsts)))).max() < 1e-8
