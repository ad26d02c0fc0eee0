"""Source models from the data: a 2-Gaussian source, point positions, per-integration fluxes."""
import numpy as np
import pytest

from mmflow.calibrate.coherency import coherencies_at_offsets, source_vector_date
from mmflow.calibrate.source_models import (ARCMIN, GaussianComponent, fit_fluxes, fit_gaussian_components,
                                            fit_point_position, gaussian_visibilities, source_uvw)
from mmflow.simulate.scene import source_points_date
from mmflow.simulate.visibilities import simulate_drift_scan
from mmflow.sky.sources import Source, Spectrum
from mmflow.telescope import Telescope
from mmflow.telescope.beams import SinElevationBeam
from mmflow.telescope.layout import Layout

FREQ = 74e6
EPOCH = 2451545.0  # J2000: the frame of date is ICRS to arcseconds


@pytest.fixture(scope="module")
def tel():
    rng = np.random.default_rng(11)
    n = 32
    r = 500 * np.sqrt(rng.uniform(size=n))
    a = rng.uniform(0, 2 * np.pi, n)
    enu = np.stack([r * np.sin(a), r * np.cos(a), np.zeros(n)], 1)
    return Telescope(Layout([f"a{k}" for k in range(n)], enu, 37.24, -118.28), SinElevationBeam(1.5), [FREQ])


def _transit_lsts(ra_deg, n, half_width_deg):
    return np.deg2rad(ra_deg + np.linspace(-half_width_deg, half_width_deg, n))


def test_two_gaussian_source_parameters_recovered(tel):
    truth = [GaussianComponent(-8.0, 3.0, 600.0, 9.0, 5.0, 30.0), GaussianComponent(10.0, -4.0, 400.0, 7.0, 6.0, -50.0)]
    total = 1000.0
    # the same source through the simulator (components sampled on grids, offsets about the centre)
    src = Source("test", 300.0, 40.0, Spectrum("power_law", (total, FREQ, 0.0)),
                 [c.as_source_component(total) for c in truth])
    pairs = tel.antenna_pairs()
    cross = pairs[:, 0] != pairs[:, 1]
    pairs = pairs[cross]
    lsts = _transit_lsts(300.0, 10, 7.5)  # one hour around transit
    vis = simulate_drift_scan(tel, FREQ, lsts, source_points_date(src, FREQ, EPOCH), pairs)
    uvw, beam = source_uvw(tel, FREQ, lsts, pairs, source_vector_date(src, EPOCH))
    # the analytic model agrees with the simulator's sampled components
    model = gaussian_visibilities(uvw, beam, truth)
    assert np.linalg.norm(model - vis) < 2e-3 * np.linalg.norm(vis)
    start = [
        GaussianComponent(-5.0, 5.0, 500.0, 12.0, 8.0, 10.0),
        GaussianComponent(12.0, -1.0, 500.0, 9.0, 9.0, -20.0),
    ]
    fit, res = fit_gaussian_components(vis, np.ones(vis.shape), uvw, beam, start, reference_flux=total)
    for f, t in zip(fit, truth):
        assert abs(f.x_arcmin - t.x_arcmin) < 0.3 and abs(f.y_arcmin - t.y_arcmin) < 0.3
        assert f.flux_jy == pytest.approx(t.flux_jy, rel=0.03)
        assert f.fwhm_major_arcmin == pytest.approx(t.fwhm_major_arcmin, rel=0.08)
        assert f.fwhm_minor_arcmin == pytest.approx(t.fwhm_minor_arcmin, rel=0.1)
        assert ((f.pa_deg - t.pa_deg + 90) % 180 - 90) == pytest.approx(0, abs=8)
    assert sum(f.flux_jy for f in fit) == pytest.approx(total)


def test_point_position_and_flux_per_integration(tel):
    rng = np.random.default_rng(5)
    pairs = tel.antenna_pairs()
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    lsts = _transit_lsts(150.0, 6, 20.0)
    src = Source("p", 150.0, 30.0, Spectrum("power_law", (200.0, FREQ, 0.0)))
    offs = rng.uniform(-15, 15, (len(lsts), 2)) * ARCMIN  # refraction, per integration
    flux = 200 * rng.uniform(0.5, 1.5, len(lsts))  # scintillation
    vis = np.stack([simulate_drift_scan(tel, FREQ, lsts[t:t + 1],
                                        source_points_date(src, FREQ, EPOCH, offs[t], flux[t] / 200), pairs)[0]
                    for t in range(len(lsts))])
    np.testing.assert_allclose(coherencies_at_offsets(tel, FREQ, lsts, src, EPOCH, offs, pairs, flux / 200), vis)
    uvw, beam = source_uvw(tel, FREQ, lsts, pairs, source_vector_date(src, EPOCH))
    off, peak = fit_point_position(vis, np.ones(vis.shape), uvw)
    assert np.abs(off - offs).max() < 0.5 * ARCMIN
    # fluxes by least squares against unit-flux models at the fitted positions
    models = coherencies_at_offsets(tel, FREQ, lsts, src, EPOCH, off, pairs, np.full(len(lsts), 1 / 200))[None]
    s = fit_fluxes(vis, np.ones(vis.shape), models)[:, 0]
    np.testing.assert_allclose(s, flux, rtol=0.01)
    np.testing.assert_allclose(peak / beam, flux, rtol=0.05)


def test_shapelet_visibilities_match_a_direct_fourier_sum():
    from mmflow.calibrate.source_models import shapelet_image, shapelet_orders, shapelet_visibilities

    beta, nmax = 10 * ARCMIN, 4
    g = np.linspace(-8 * beta, 8 * beta, 321)
    x, y = np.meshgrid(g, g)
    dA = (g[1] - g[0]) ** 2
    rng = np.random.default_rng(0)
    uvw = np.zeros((1, 6, 3))
    uvw[0, :, :2] = rng.uniform(-100, 100, (6, 2))
    vis = shapelet_visibilities(uvw, np.ones(1), beta, nmax)[:, 0]
    for k, _ in enumerate(shapelet_orders(nmax)):
        c = np.zeros(len(shapelet_orders(nmax)))
        c[k] = 1.0
        img = shapelet_image(c, x, y, beta, nmax)
        direct = np.array([np.sum(img * np.exp(2j * np.pi * (u * x + v * y))) * dA for u, v in uvw[0, :, :2]])
        np.testing.assert_allclose(vis[k], direct, atol=1e-6 * np.abs(direct).max() + 1e-12)


def test_sun_disc_fitted_by_shapelets(tel):
    from mmflow.calibrate.source_models import fit_shapelets
    from mmflow.simulate.corrupt import _sun_vector_date, sun_points

    jd = 2457700.5 + 20.5 / 24  # the Sun near transit at OVRO
    sun = sun_points(jd, FREQ)
    pairs = tel.antenna_pairs()
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    vsun = _sun_vector_date(jd)
    ra = np.rad2deg(np.arctan2(vsun[1], vsun[0]))
    lsts = _transit_lsts(ra, 4, 3.0)
    vis = simulate_drift_scan(tel, FREQ, lsts, sun, pairs)
    uvw, beam = source_uvw(tel, FREQ, lsts, pairs, vsun)
    coeffs, model = fit_shapelets(vis, np.ones(vis.shape), uvw, beam, beta=12 * ARCMIN, nmax=10)
    assert np.linalg.norm(vis - model) < 0.02 * np.linalg.norm(vis)
    # flux: the model's zero-spacing visibility over the beam
    zero = np.zeros((1, 1, 3))
    from mmflow.calibrate.source_models import shapelet_visibilities

    total = (coeffs @ shapelet_visibilities(zero, np.ones(1), 12 * ARCMIN, 10)[:, 0, 0]).real
    assert total == pytest.approx(sun.flux_jy.sum(), rel=0.02)
    assert total > sun_points(jd, FREQ / 2).flux_jy.sum()  # positive spectral index


def test_position_gains_move_the_model_to_the_fitted_position(tel):
    """``position_gains``: the fitted offsets as DD phase gradients; ``h_i conj(h_j) M`` equals the
    simulator's source at the true offset to the fit's precision (offsets within 0.5')."""
    from mmflow.simulate.corrupt import gain_products
    from mmflow.calibrate.source_models import position_gains

    rng = np.random.default_rng(8)
    pairs = tel.antenna_pairs()
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    lsts = _transit_lsts(150.0, 5, 20.0)
    src = Source("p", 150.0, 30.0, Spectrum("power_law", (200.0, FREQ, 0.0)))
    offs = rng.uniform(-15, 15, (len(lsts), 2)) * ARCMIN
    vis = np.stack([simulate_drift_scan(tel, FREQ, lsts[t:t + 1], source_points_date(src, FREQ, EPOCH, offs[t]),
                                        pairs)[0] for t in range(len(lsts))])
    model = coherencies_at_offsets(tel, FREQ, lsts, src, EPOCH, np.zeros((len(lsts), 2)), pairs)
    off, h = position_gains(tel, FREQ, lsts, pairs, source_vector_date(src, EPOCH), vis, np.ones(vis.shape))
    assert np.abs(off - offs).max() < 0.5 * ARCMIN
    moved = gain_products(h[..., None], pairs)[..., 0] * model
    before = np.linalg.norm(vis - model) / np.linalg.norm(vis)
    after = np.linalg.norm(vis - moved) / np.linalg.norm(vis)
    print(f"model at the catalogue position leaves {before:.3f} of the source, moved {after:.4f}")
    assert after < 0.05 * before
