"""The polarisation convention of input files and the flux scale (issue 24 item 5).

matvis (like pyuvsim and hera_sim) writes an unpolarised source of flux S as XX = YY = S B / 2
(pyuvdata's ``pol_convention = "sum"``: I = XX + YY); CASA-style data XX = S B ("avg"). mmflow
stores and models the avg convention and doubles "sum" data on ingest. Before, a matvis file imaged
without calibration came out at half its flux (CLEANed fluxes 0.49-0.50 of the simulated ones).
"""
import numpy as np
import pytest
import zarr

from mmflow.errors import InputError
from mmflow.io.polarization import pol_factor
from mmflow.sky.sources import get_sources
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.uvh5_helpers import gaussian_power_beamfits, matvis_uvdata

QUIET = dict(progress=False, log=lambda *a: None)
NAMES = ["Cyg A", "Cas A", "Vir A", "Tau A"]
N_TIMES, LMAX = 500, 48


def test_pol_factor_follows_the_file_or_the_setting_and_never_guesses():
    assert pol_factor("sum", "auto", False, "f") == (2.0, "sum")
    assert pol_factor("avg", "auto", False, "f") == (1.0, "avg")
    assert pol_factor(None, "sum", False, "f") == (2.0, "sum")  # the user says
    assert pol_factor("avg", "sum", False, "f") == (2.0, "sum")  # and overrides a file's
    assert pol_factor(None, "auto", True, "f") == (1.0, "avg")  # calibration sets the flux scale
    with pytest.raises(InputError) as err:
        pol_factor(None, "auto", False, "scan.uvh5")
    assert "input.pol_convention=sum" in str(err.value) and "scan.uvh5" in str(err.value)


def _sin_elevation_beamfits(path, alpha=1.5):
    uvb = gaussian_power_beamfits(path)
    uvb.data_array[:] = (np.clip(np.cos(uvb.axis2_array), 0, None) ** alpha)[None, None, None, :, None]
    uvb.write_beamfits(str(path), clobber=True)
    return uvb


@pytest.fixture(scope="module")
def matvis_scan(tmp_path_factory):
    """The four brightest sources at 40 MHz, one sidereal day, 20 m of the OVRO-LWA core, XX only,
    written by pyuvdata with matvis's own convention (pol_convention "sum") and without it."""
    root = tmp_path_factory.mktemp("fluxconv")
    beam = _sin_elevation_beamfits(root / "sin_el.fits")
    srcs = get_sources(NAMES)
    sources = tuple((s.ra_deg, s.dec_deg, float(s.flux(40e6, 2017.1))) for s in srcs)
    uv, _ = matvis_uvdata(beam, n_times=N_TIMES, radius_m=20.0, sources=sources)
    uv.write_uvh5(str(root / "sum.uvh5"), clobber=True, fix_autos=True)
    uv.pol_convention = None
    uv.write_uvh5(str(root / "unknown.uvh5"), clobber=True, fix_autos=True)
    return root, sources


def _cfg(run_dir, data, *extra):
    return load_config("workflows/uvh5-image.yaml", [
        f"run.directory={run_dir}", f"input.path={data}", f"mmode.lmax={LMAX}", "mmode.splits=[full, even, odd]",
        "transfer.dtype=float64", "transfer.noise_weighting=false", "imaging.lcurve=false", "products.nside=64",
        "products.png=false", "cluster.kind=synchronous", "beam={type: sin_elevation, alpha: 1.5}",
        "clean.enabled=true", "clean.rel_threshold=1e-3", "clean.min_separation_deg=15", "products.flux_scale=false",
        *extra])


def test_unknown_convention_without_calibration_is_refused_before_work(matvis_scan, tmp_path):
    root, _ = matvis_scan
    with pytest.raises(InputError, match="pol_convention"):
        run_workflow(_cfg(tmp_path / "r", root / "unknown.uvh5"), **QUIET)
    assert not (tmp_path / "r" / "vis.zarr").exists()


def test_matvis_scan_cleaned_without_calibration_gives_the_simulated_fluxes(matvis_scan, tmp_path):
    """Ingested with its own pol_convention ("sum"): XX doubled on ingest, and the CLEANed flux of each
    source within 2 % of the flux matvis simulated (it was ~0.5 before)."""
    from mmflow.conventions import radec_to_vec
    from mmflow.imaging import psf
    from mmflow.workflow.engine import clean_state as cs

    root, sources = matvis_scan
    run_dir = tmp_path / "sum"
    cfg = _cfg(run_dir, root / "sum.uvh5")
    run_workflow(cfg, **QUIET)
    vis = zarr.open_group(str(run_dir / "vis.zarr"), mode="r")
    assert vis.attrs["pol_convention"] == "sum" and vis.attrs["pol_factor"] == 2.0
    from astropy.io import fits

    with fits.open(next((run_dir / "maps").glob("map_*.fits"))) as hdul:  # the convention is stated
        h = hdul[1].header
        assert (h["STOKES"], h["POLCONV"], h["POLIN"]) == ("I", "avg", "sum")
    g = zarr.open_group(str(run_dir / "clean.zarr"), mode="r")
    state, reason = cs.clean_result(g, 0, cs.clean_options(cfg.clean), int(g["n_cycles"][0]))
    table = psf.table_from_array(g["psf_table"][0, 0])
    ratios = []
    for ra, dec, flux in sources:
        v = radec_to_vec(np.deg2rad(ra), np.deg2rad(dec))  # ICRS; precession to 2017 is far below a FWHM
        fwhm = psf.interp_table(table, np.arcsin(v[2]), "major")
        near = np.arccos(np.clip(state.comp_vec @ v, -1, 1)) < fwhm
        ratios.append(state.comp_flux[near].sum() / flux)
    print("CLEANed / simulated flux:", np.round(ratios, 4))
    np.testing.assert_allclose(ratios, 1.0, atol=0.02)
    # told the opposite convention, the same file is imaged at half the flux: the setting is used
    half = tmp_path / "avg"
    cfg_avg = _cfg(half, root / "sum.uvh5", "input.pol_convention=avg")
    run_workflow(cfg_avg, **QUIET)
    a_sum = zarr.open_group(str(run_dir / "alm.zarr"), mode="r")["alm"][0, 0]
    a_avg = zarr.open_group(str(half / "alm.zarr"), mode="r")["alm"][0, 0]
    np.testing.assert_allclose(a_avg, a_sum / 2, rtol=1e-9, atol=1e-12 * np.abs(a_sum).max())
