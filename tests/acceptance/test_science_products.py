"""The products stage's science products across channels and from the peel solutions.

A diffuse sky with one spectral index (beta = -2.5 everywhere, mmflow's synthetic Galaxy)
seen at three frequencies: the T-T spectral-index map recovers it and the three-colour
Mollweide is drawn, both in the report. Peeled and subtracted sources, no longer in the map,
get their flux from the per-integration peel solutions.
"""
import json

import healpy
import numpy as np
import pytest

from mmflow.analysis.fluxscale import peel_flux_factors
from mmflow.io.report import check_report, png_size, summary_from_run
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import small_config

QUIET = dict(progress=False, log=lambda *a: None)
BETA = -2.5  # mmflow.sky.diffuse.synthetic_sky_kelvin's index


@pytest.fixture(scope="module")
def three_channels(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("science") / "three"
    cfg = small_config(run_dir, "observation.freqs_mhz=[40.0, 50.0, 60.0]", "sky.sources=[]", "sky.noise=false",
                       "products.frame=galactic", "products.flux_scale=false", "products.spectral_index_nside=16",
                       "imaging.lcurve=false")
    run_workflow(cfg, **QUIET)
    return run_dir, cfg


def test_spectral_index_of_a_sky_with_one_index_is_recovered(three_channels):
    run_dir, _ = three_channels
    si = json.loads((run_dir / "maps" / "summary.json").read_text())["spectral_index"]
    assert si["freqs_hz"] == [40e6, 60e6] and si["input"] == "map"
    beta = healpy.read_map(str(run_dir / si["files"]["beta (FITS)"]))
    r2 = healpy.read_map(str(run_dir / si["files"]["r2 (FITS)"]))
    assert healpy.npix2nside(len(beta)) == 16
    good = (beta != healpy.UNSEEN) & (r2 > 0.9)
    print(f"R^2 > 0.9 on {good.mean():.3f} of the sky; beta there: median {np.median(beta[good]):.4f}, "
          f"quartiles {np.percentile(beta[good], [25, 75]).round(4).tolist()}")
    assert good.mean() > 0.5  # measured 0.89 at nside 32
    assert np.median(beta[good]) == pytest.approx(BETA, abs=0.05)  # measured -2.535
    assert si["beta_median_r2_above_0.9"] == pytest.approx(np.median(beta[good]), abs=1e-6)
    # the never-seen sky has no index: no region without a seen pixel has one
    seen = healpy.read_map(str(run_dir / "maps" / "map_40.000MHz.fits")) != healpy.UNSEEN
    blind = [p for p in range(len(beta))
             if not seen[healpy.query_disc(32, healpy.pix2vec(16, p), np.deg2rad(10.0))].any()]
    assert len(blind) > 50 and np.all(beta[blind] == healpy.UNSEEN)


def test_three_colour_and_spectral_index_figures_are_in_the_report(three_channels):
    run_dir, _ = three_channels
    s = summary_from_run(run_dir)
    paths = [f.path for f in s.spectral_index]
    assert paths == ["maps/spectral_index.png", "maps/three_colour.png"]
    for p in paths:
        w, h = png_size((run_dir / p).read_bytes())
        assert w > 400 and h > 200
    report = run_dir / "maps" / "report.html"
    assert check_report(report) == []
    page = report.read_text()
    assert 'id="spectral"' in page and 'src="three_colour.png"' in page and 'href="spectral_index_beta.fits"' in page
    assert "fluxscale" not in page  # products.flux_scale=false


def test_peel_flux_factor_of_known_gains():
    rng = np.random.default_rng(3)
    n_t, n_ant = 5, 12
    amp = np.sqrt(np.array([1.2, 0.8, 1.0, 1.1, 0.9]))
    gains = amp[:, None] * np.exp(1j * rng.uniform(0, 2 * np.pi, (n_t, n_ant)))  # phases do not matter
    mode = np.array([1, 1, 2, 0, 1])
    scale = np.array([9.0, 9.0, 0.7, 9.0, 9.0])
    f = peel_flux_factors(mode, scale, gains)
    np.testing.assert_allclose(f[[0, 1, 4]], amp[[0, 1, 4]] ** 2, rtol=1e-12)
    assert f[2] == 0.7 and np.isnan(f[3])
    # unequal amplitudes: the mean of |h_i| |h_j| over the N (N - 1) / 2 baselines
    a = rng.uniform(0.5, 1.5, n_ant)
    i, j = np.triu_indices(n_ant, 1)
    assert peel_flux_factors([1], [0.0], a[None])[0] == pytest.approx(np.mean(a[i] * a[j]), rel=1e-12)


def test_peeled_and_subtracted_sources_are_measured_from_the_peel_solutions(tmp_path):
    """Noiseless, uncorrupted data: the peel solutions hold each source at its published flux."""
    run_dir = tmp_path / "peel"
    cfg = small_config(run_dir, "peel.enabled=true", "peel.sources=[Cyg A, Cas A]", "peel.peel=[Cyg A]",
                       "peel.min_baseline_lambda=1", "sky.noise=false", "sky.diffuse=false", "products.png=false",
                       "products.flux_scale=true", "products.flux_scale_sources=[Cyg A, Cas A, Vir A]",
                       "imaging.lcurve=false")
    run_workflow(cfg, **QUIET)
    rows = {r["name"]: r for r in json.loads((run_dir / "maps" / "fluxscale.json").read_text())}
    assert set(rows) == {"Cyg A", "Cas A", "Vir A"}
    assert rows["Cyg A"]["method"].startswith("peel (") and rows["Cas A"]["method"].startswith("peel (")
    assert rows["Vir A"]["method"] == "map"
    for name in ("Cyg A", "Cas A"):
        print(name, rows[name]["ratio"], rows[name]["measured_err_jy"])
        assert rows[name]["ratio"] == pytest.approx(1.0, abs=0.01)  # measured 1.000 and 0.999
        assert 0 <= rows[name]["measured_err_jy"] < 0.01 * rows[name]["model_jy"]


def test_alm_sampler_equals_the_rotated_map_at_its_pixels():
    """The flux scale evaluates PSFs and noise only at the disc and annulus pixels: the same
    values as drawing the alm rotated to the map's frame, in the map's unit."""
    from mmflow.analysis.fluxscale import alm_sampler, disc_minus_annulus
    from mmflow.imaging.maps import alm_to_output_map
    from mmflow.sky.diffuse import band_limited_random_alm
    from mmflow.sky.frames import rotation_matrix
    from mmflow.sky.units import convert

    lmax, nside, epoch, freq = 24, 32, 2457802.0, 40e6
    alm = band_limited_random_alm(lmax, seed=4)
    alm[: lmax + 1] = alm[: lmax + 1].real  # a real sky: a_l0 real
    full = alm_to_output_map(alm, lmax, freq, epoch, "galactic", "K", nside)
    sampler = alm_sampler(alm, lmax, nside, rotation_matrix("date", "galactic", epoch).T,
                          float(convert(1.0, "Jy/sr", "K", freq)))
    pix = np.arange(0, len(full), 7)
    np.testing.assert_allclose(sampler(pix), full[pix], rtol=1e-9, atol=1e-9 * np.abs(full).max())
    v = np.array(healpy.pix2vec(nside, 1000))
    assert disc_minus_annulus(sampler, v, 0.2, (0.3, 0.5), nside) == pytest.approx(
        disc_minus_annulus(full, v, 0.2, (0.3, 0.5)), rel=1e-9)
