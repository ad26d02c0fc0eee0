"""Flux scale through the real imaging PSF: catalogue sources injected with known fluxes into a
Tikhonov map (ICRS output of a frame-of-date solution) are recovered by disc-minus-annulus over
the PSF's sum, and the flux-scale figure shows them over their published spectra."""
import healpy
import numpy as np
import pytest

from mmflow.analysis.fluxscale import flux_scale_rows, psf_map_function
from mmflow.analysis.peaks import measure_peak
from mmflow.imaging import psf
from mmflow.io.report import png_size
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.sky.frames import rotate_alm, rotation_matrix
from mmflow.sky.harmonics import point_sources_alm
from mmflow.sky.sources import get_sources
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.beams import SinElevationBeam

LMAX, NSIDE, FREQ = 64, 64, 40e6
# sources of comparable flux at 40 MHz (0.17-1.5 kJy), >= 25 deg apart: each one's sidelobes
# at the others stay below 1 % of their flux for this 26-antenna core (FWHM ~6 deg)
NAMES = ["3C 123", "3C 196", "Hya A", "Her A", "3C 380"]
FACTORS = np.array([1.0, 1.2, 0.9, 1.05, 0.8])  # injected / catalogue spectrum


@pytest.fixture(scope="module")
def observed():
    tel = Telescope(ovro_lwa_layout("core", radius_m=25), SinElevationBeam(1.5), [FREQ])
    acc = accumulate_normal_equations(tel, FREQ, np.zeros((LMAX + 1, 2, len(tel.antenna_pairs())), complex), LMAX)
    ops = psf.block_operators(acc, 1e-2)
    srcs = get_sources(NAMES)
    icrs_to_date = rotation_matrix("icrs", "date", 2460000.5)
    true = np.array([float(s.flux(FREQ)) for s in srcs]) * FACTORS
    sky = point_sources_alm(np.array([icrs_to_date @ s.vector_icrs() for s in srcs]), true, LMAX)
    ell = np.arange(LMAX + 1)
    np.random.seed(5)  # healpy.synalm draws from numpy's global generator
    diffuse = healpy.synalm(np.r_[0.0, 0.0, 50.0 * (ell[2:] / 2.0) ** -2.5], lmax=LMAX)  # smooth background
    dirty_date = psf.observe_alm(ops, sky + diffuse, LMAX)
    hmap = healpy.alm2map(rotate_alm(dirty_date, icrs_to_date.T, LMAX), NSIDE, lmax=LMAX)  # the ICRS map
    return hmap, srcs, true, psf_map_function(ops, LMAX, NSIDE, map_to_date=icrs_to_date)


def test_injected_fluxes_recovered_through_the_psf_normalisation(observed):
    hmap, srcs, true, psf_map_at = observed
    v = srcs[0].vector_icrs()
    fwhm = measure_peak(psf_map_at(v), v, np.deg2rad(10))["fwhm_rad"]
    assert np.rad2deg(fwhm) == pytest.approx(6.0, abs=1.0)
    rows = flux_scale_rows(hmap, srcs, psf_map_at, FREQ, 0.8 * fwhm, (1.2 * fwhm, 2.0 * fwhm))
    got = np.array([r["measured_jy"] for r in rows])
    print("measured / injected:", np.round(got / true, 4).tolist())
    np.testing.assert_allclose(got / true, 1.0, atol=0.03)
    np.testing.assert_allclose([r["ratio"] for r in rows], FACTORS, rtol=0.03)
    # the PSF normalisation matters: the disc sum of the map alone is off by the PSF's disc sum
    from mmflow.analysis.fluxscale import disc_minus_annulus

    raw = disc_minus_annulus(hmap, v, 0.8 * fwhm, (1.2 * fwhm, 2.0 * fwhm))
    assert abs(raw / true[0] - 1) > 0.5


def test_flux_scale_figure_shows_each_source_over_its_spectrum(observed, tmp_path):
    from mmflow.io.plots import write_flux_scale_png

    hmap, srcs, true, psf_map_at = observed
    v = srcs[0].vector_icrs()
    fwhm = measure_peak(psf_map_at(v), v, np.deg2rad(10))["fwhm_rad"]
    rows = flux_scale_rows(hmap, srcs, psf_map_at, FREQ, 0.8 * fwhm, (1.2 * fwhm, 2.0 * fwhm))
    # a second channel, as a multi-frequency run has: the spectrum times the same factors
    rows += [dict(r, freq_hz=60e6, measured_jy=f * float(s.flux(60e6))) for r, s, f in zip(rows, srcs, FACTORS)]
    out = write_flux_scale_png(tmp_path / "fluxscale.png", rows)
    assert out["panels"] == NAMES and out["points"] == 2 * len(NAMES)
    for name, f in zip(NAMES, FACTORS):
        assert out["median_ratio"][name] == pytest.approx(f, rel=0.03)
    w, h = png_size((tmp_path / "fluxscale.png").read_bytes())
    assert w > 600 and h > 250
