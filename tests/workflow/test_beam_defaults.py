"""Beams without settings (issue 39 item 5): an ingest run's channels are the data's, and pyuvdata's
analytic beams that take no size are accepted.

A drift scan simulated by matvis (an independent simulator) at one frequency, 50 MHz (not the
simulate default of 40 MHz), through the Stokes-I power beam of crossed short dipoles,
``(XX + YY) / 2`` of pyuvdata's ``ShortDipoleBeam`` tabulated by pyuvdata on a 1 x 0.5 degree
grid and written as a one-frequency beamfits file. Imaged with no ``observation.freqs_mhz``:
with that file, and with ``beam={type: pyuvdata, class: ShortDipoleBeam}`` (no ``params``).
"""
import numpy as np
import pytest
import zarr

from mmflow.analysis.peaks import measure_peak
from mmflow.conventions import radec_to_vec
from mmflow.errors import InputError
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.uvh5_helpers import matvis_uvdata

FREQ_HZ = 50e6
SOURCES = ((60.0, 45.0, 500.0), (200.0, 30.0, 400.0), (300.0, 60.0, 450.0))
QUIET = dict(progress=False, log=lambda *a: None)


def _dipole_power_beamfits(path, freqs_hz=(FREQ_HZ,)):
    """pyuvdata's ShortDipoleBeam tabulated as a power beam, its Stokes-I ``(XX + YY) / 2`` as one
    polarisation (what matvis and mmflow's one-polarisation path both take as the beam)."""
    from pyuvdata.analytic_beam import ShortDipoleBeam

    uvb = ShortDipoleBeam().to_uvbeam(freq_array=np.asarray(freqs_hz), beam_type="power",
                                      axis1_array=np.deg2rad(np.arange(0, 360, 1.0)),
                                      axis2_array=np.deg2rad(np.arange(0, 90.01, 0.5)))
    pols = list(uvb.polarization_array)
    avg = 0.5 * (uvb.data_array[:, pols.index(-5)] + uvb.data_array[:, pols.index(-6)])
    uvb.select(polarizations=[-5])
    uvb.data_array[:, 0] = avg
    uvb.write_beamfits(str(path), clobber=True)
    return uvb


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    root = tmp_path_factory.mktemp("beam_defaults")
    beam = _dipole_power_beamfits(root / "dipole50.fits")
    uv, _ = matvis_uvdata(beam, n_times=96, radius_m=12.0, freq_hz=FREQ_HZ, sources=SOURCES)
    uv.write_uvh5(str(root / "scan50.uvh5"), clobber=True, fix_autos=True)
    return root


def _cfg(run_dir, data, beam):
    return load_config("workflows/uvh5-image.yaml", [
        f"run.directory={run_dir}", f"input.path={data}", f"beam={beam}", "mmode.lmax=24",
        "products.nside=32", "products.png=false", "products.unit=Jy/sr",
        "cluster.kind=synchronous"])


def _map(run_dir):
    import healpy

    return healpy.read_map(str(run_dir / "maps" / "map_50.000MHz.fits"))


@pytest.fixture(scope="module")
def file_run(scan):
    run = scan / "file-beam"
    cfg = _cfg(run, scan / "scan50.uvh5", f"{{type: pyuvdata, file: {scan / 'dipole50.fits'}}}")
    assert cfg.observation.freqs_mhz is None
    run_workflow(cfg, **QUIET)
    return run


def test_one_frequency_file_with_its_beam_file_images_without_freqs_mhz(scan, file_run):
    np.testing.assert_array_equal(zarr.open_group(str(file_run / "vis.zarr"), mode="r")["freqs_hz"][:], [FREQ_HZ])
    hmap = _map(file_run)
    for ra, dec, _ in SOURCES:  # every source where matvis put it
        pk = measure_peak(hmap, radec_to_vec(np.deg2rad(ra), np.deg2rad(dec)), np.deg2rad(15))
        print(f"({ra}, {dec}): {pk['offset_rad'] / pk['fwhm_rad']:.3f} FWHM from the truth")
        assert pk["offset_rad"] < 0.15 * pk["fwhm_rad"], (ra, dec, pk["offset_rad"] / pk["fwhm_rad"])
    # a beam file that misses the data's channel is refused before any work, naming both
    _dipole_power_beamfits(scan / "dipole60.fits", (60e6,))
    with pytest.raises(InputError, match="50.000 MHz outside the beam's 60.000-60.000 MHz"):
        _cfg(scan / "refused", scan / "scan50.uvh5", f"{{type: pyuvdata, file: {scan / 'dipole60.fits'}}}")
    assert not (scan / "refused").exists()


def test_short_dipole_class_without_params_is_accepted_and_used(scan, file_run):
    run = scan / "class-beam"
    cfg = _cfg(run, scan / "scan50.uvh5", "{type: pyuvdata, class: ShortDipoleBeam}")
    assert cfg.beam.params() == {"class": "ShortDipoleBeam"}
    run_workflow(cfg, **QUIET)
    ref, hmap = _map(file_run), _map(run)
    seen = ref != -1.6375e30
    print(f"class vs file: {np.std((hmap - ref)[seen]) / np.std(ref[seen]):.2e}")
    # the analytic beam gives the map of pyuvdata's own tabulation of it (interpolated on 1 x 0.5 deg)
    assert np.std((hmap - ref)[seen]) < 0.01 * np.std(ref[seen])
    # ... and not that of another beam: the same data imaged through the default sin(elevation)^1.5
    other = scan / "sin-elevation"
    run_workflow(_cfg(other, scan / "scan50.uvh5", "{type: sin_elevation, alpha: 1.5}"), **QUIET)
    print(f"sin_elevation vs file: {np.std((_map(other) - ref)[seen]) / np.std(ref[seen]):.2e}")
    assert np.std((_map(other) - ref)[seen]) > 0.05 * np.std(ref[seen])


def test_analytic_beams_that_need_a_size_are_refused_by_their_signature(tmp_path):
    with pytest.raises(InputError, match="AiryBeam needs diameter in 'params'"):
        _cfg(tmp_path / "r", tmp_path / "none.uvh5", "{type: pyuvdata, class: AiryBeam}")
    for cls in ("ShortDipoleBeam", "UniformBeam"):
        _cfg(tmp_path / "r", tmp_path / "none.uvh5", f"{{type: pyuvdata, class: {cls}}}")
