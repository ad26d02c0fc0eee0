"""Ingest UVH5 drift scans (matvis-simulated) and image them; bad inputs give clear errors."""
import shutil

import numpy as np
import pytest

from mmflow.analysis.peaks import measure_peak
from mmflow.conventions import radec_to_vec
from mmflow.errors import CoverageError, InputError
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.uvh5_helpers import gaussian_power_beamfits, matvis_drift_scan

SOURCES = ((60.0, 45.0, 500.0), (200.0, 30.0, 400.0), (300.0, 60.0, 450.0))


BEAM = {}


def _cfg(run_dir, pattern, *extra):
    beam_file = BEAM["file"]
    return load_config("workflows/uvh5-image.yaml", [
        f"run.directory={run_dir}", f"input.path={pattern}", "mmode.lmax=64", "transfer.dtype=float64",
        "transfer.m_block=8", "imaging.eps=0.0001", "transfer.noise_weighting=false", "imaging.filter_m0=false",
        "products.nside=256", "products.png=false", "products.unit=Jy/sr", "cluster.kind=synchronous",
        f"beam={{type: pyuvdata, file: {beam_file}}}", *extra])


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    root = tmp_path_factory.mktemp("scan")
    (root / "beam").mkdir()
    BEAM["file"] = str(root / "beam" / "gauss_power.fits")
    beam = gaussian_power_beamfits(BEAM["file"])
    d = root / "uvh5"
    d.mkdir()
    paths, lay = matvis_drift_scan(d, beam, n_times=140, radius_m=20.0, sources=SOURCES)
    return d, paths


def test_matvis_uvh5_drift_scan_images_sources_at_their_icrs_positions(scan, tmp_path):
    """matvis (an independent simulator) -> UVH5 -> ingest -> image: positions and sign convention."""
    import healpy

    d, _ = scan
    run_workflow(_cfg(tmp_path / "run", str(d / "*.uvh5")), progress=False, log=lambda *a: None)
    hmap = healpy.read_map(str(tmp_path / "run" / "maps" / "map_40.000MHz.fits"))
    for ra, dec, _ in SOURCES:
        v = radec_to_vec(np.deg2rad(ra), np.deg2rad(dec))
        pk = measure_peak(hmap, v, np.deg2rad(12))
        assert pk["offset_rad"] < 0.1 * pk["fwhm_rad"], (ra, dec, np.rad2deg(pk["offset_rad"]))
    # the opposite sign convention mirrors the sky: the sources are then far from where they belong
    run_workflow(_cfg(tmp_path / "conj", str(d / "*.uvh5"), "input.conjugate=true"), progress=False,
                 log=lambda *a: None)
    wrong = healpy.read_map(str(tmp_path / "conj" / "maps" / "map_40.000MHz.fits"))
    v = radec_to_vec(np.deg2rad(SOURCES[0][0]), np.deg2rad(SOURCES[0][1]))
    assert (
        measure_peak(wrong, v, np.deg2rad(12))["offset_rad"] > measure_peak(hmap, v, np.deg2rad(12))["fwhm_rad"] * 0.3
    )


def test_plan_of_ingested_files_counts_their_array(scan, tmp_path):
    """`mmflow plan` of ingested files plans the files' antennas and baselines (not the configuration's
    telescope section, which ingest ignores)."""
    from pyuvdata import UVData

    from mmflow.workflow.plan.planner import geometry

    d, paths = scan
    uv = UVData.from_file(str(paths[0]))
    n_ant = len(set(uv.ant_1_array) | set(uv.ant_2_array))
    g = geometry(_cfg(tmp_path / "run", str(d / "*.uvh5")))
    assert (g.n_ant, g.n_bl, g.n_time) == (n_ant, n_ant * (n_ant + 1) // 2, 140)


def test_corrupt_file_is_named_or_skipped_and_counted(scan, tmp_path):
    d, paths = scan
    bad = tmp_path / "uvh5"
    shutil.copytree(d, bad)
    (bad / "scan_002.uvh5").write_bytes(b"not an hdf5 file")
    with pytest.raises(InputError, match=r"scan_002.uvh5.*cannot read.*on_bad_file=skip"):
        run_workflow(_cfg(tmp_path / "r1", str(bad / "*.uvh5")), progress=False, log=lambda *a: None)
    # skipping loses 1/6 of the day: refused where the coverage asked for is more, imaged with the default 0.7
    with pytest.raises(CoverageError):
        run_workflow(_cfg(tmp_path / "r2", str(bad / "*.uvh5"), "input.on_bad_file=skip", "mmode.min_coverage=0.9"),
                     progress=False, log=lambda *a: None)
    run_workflow(_cfg(tmp_path / "r3", str(bad / "*.uvh5"), "input.on_bad_file=skip"),
                 progress=False, log=lambda *a: None)
    import zarr

    attrs = zarr.open_group(str(tmp_path / "r3" / "vis.zarr"), mode="r").attrs
    assert len(attrs["skipped_files"]) == 1 and "scan_002" in attrs["skipped_files"][0]


def test_flags_that_leave_most_baselines_half_a_day_stop_naming_the_flags(scan, tmp_path):
    """The integrations cover the day but the input's flags cut most baselines to half of it: the
    mmodes stage stops saying the flags are short, not the observation (its earlier message, "observe
    a full sidereal day", named a symptom), and only after the stage's chunks have run."""
    from pyuvdata import UVData

    d, paths = scan
    flagged = tmp_path / "flagged"
    flagged.mkdir()
    for k, path in enumerate(paths):
        uv = UVData.from_file(str(path))
        if k >= len(paths) // 2:  # the second half of the day: every baseline of antennas 0..9 flagged
            bad = (uv.ant_1_array < 10) | (uv.ant_2_array < 10)
            uv.flag_array[bad] = True
        uv.write_uvh5(str(flagged / path.name))
    with pytest.raises(CoverageError, match=r"keep less than 70% of the sidereal day after their flags, though the "
                                            r"integrations cover the day: the flags, not the observation"):
        run_workflow(_cfg(tmp_path / "run", str(flagged / "*.uvh5")), progress=False, log=lambda *a: None)
    assert not (tmp_path / "run" / "partials.zarr").exists()


def test_mixed_frequencies_and_duplicate_times_are_rejected(scan, tmp_path):
    from pyuvdata import UVData

    d, paths = scan
    mixed = tmp_path / "uvh5"
    shutil.copytree(d, mixed)
    uv = UVData.from_file(str(mixed / "scan_004.uvh5"))
    uv.freq_array = uv.freq_array + 0.25 * uv.channel_width  # overlapping, not equal: not a subband either
    uv.write_uvh5(str(mixed / "scan_004.uvh5"), clobber=True)
    with pytest.raises(InputError, match=r"scan_004.uvh5.*freq_array.*overlap"):
        run_workflow(_cfg(tmp_path / "r1", str(mixed / "*.uvh5")), progress=False, log=lambda *a: None)
    dup = tmp_path / "dup" / "uvh5"
    shutil.copytree(d, dup)
    shutil.copy(dup / "scan_001.uvh5", dup / "scan_001_copy.uvh5")
    with pytest.raises(InputError, match=r"time_array.*also in"):
        run_workflow(_cfg(tmp_path / "r2", str(dup / "*.uvh5")), progress=False, log=lambda *a: None)


def test_missing_input_and_flagged_integrations(scan, tmp_path):
    from pyuvdata import UVData

    d, _ = scan
    with pytest.raises(InputError, match="no files match"):
        run_workflow(_cfg(tmp_path / "r0", str(tmp_path / "nothing*.uvh5")), progress=False, log=lambda *a: None)
    flagged = tmp_path / "uvh5"
    shutil.copytree(d, flagged)
    uv = UVData.from_file(str(flagged / "scan_000.uvh5"))
    uv.flag_array[:] = True
    uv.write_uvh5(str(flagged / "scan_000.uvh5"), clobber=True)
    summaries = run_workflow(_cfg(tmp_path / "r1", str(flagged / "*.uvh5"), "mmode.min_coverage=0.8"),
                             progress=False, log=lambda *a: None)
    from mmflow.workflow.engine.rundir import RunDir

    done = RunDir(tmp_path / "r1").task_infos("ingest")
    assert sum(x["fully_flagged_integrations"] for x in done.values()) == 24  # 140 integrations / 6 files
    assert summaries["products"]["tasks_run"] == 1


def test_antenna_sets_must_agree_but_missing_baselines_are_unmeasured(scan, tmp_path):
    from pyuvdata import UVData

    d, _ = scan
    other = tmp_path / "other" / "uvh5"
    shutil.copytree(d, other)
    uv = UVData.from_file(str(other / "scan_003.uvh5"))
    uv.select(antenna_nums=uv.telescope.antenna_numbers[:-2], keep_all_metadata=False)
    uv.write_uvh5(str(other / "scan_003.uvh5"), clobber=True)
    with pytest.raises(InputError, match=r"scan_003.uvh5.*antenna_numbers.*antenna set differs"):
        run_workflow(_cfg(tmp_path / "r1", str(other / "*.uvh5")), progress=False, log=lambda *a: None)
    fewer = tmp_path / "fewer" / "uvh5"
    shutil.copytree(d, fewer)
    uv = UVData.from_file(str(fewer / "scan_003.uvh5"))
    keep = [(i, j) for i, j in uv.get_antpairs() if j != uv.telescope.antenna_numbers[-1]]
    uv.select(bls=keep)  # same antenna table, fewer baselines
    uv.write_uvh5(str(fewer / "scan_003.uvh5"), clobber=True)
    run_workflow(_cfg(tmp_path / "r2", str(fewer / "*.uvh5"), "mmode.min_coverage=0.8"), progress=False,
                 log=lambda *a: None)
    import zarr

    g = zarr.open_group(str(tmp_path / "r2" / "vis.zarr"), mode="r")
    w = g["weights"][:, :, 0].min(axis=-1)
    last = int(g["pairs"][:].max())
    lacking = np.flatnonzero(g["pairs"][:, 1] == last)
    assert np.all(w[:, lacking].sum(axis=0) < w.shape[0])  # unmeasured in scan_003's integrations
    assert np.all(w[:, lacking].sum(axis=0) > 0.8 * w.shape[0])


@pytest.mark.parametrize("policy", ["drop", "downweight"])
def test_a_low_coverage_baseline_never_gains_weight(scan, tmp_path, policy):
    """One baseline flagged in 5 of 6 files (17 % coverage): dropped or down-weighted, counted and logged."""
    from pyuvdata import UVData
    import zarr

    d, _ = scan
    flagged = tmp_path / "uvh5"
    shutil.copytree(d, flagged)
    for k in range(1, 6):
        uv = UVData.from_file(str(flagged / f"scan_{k:03d}.uvh5"))
        uv.flag_array[uv.antpair2ind(0, 3)] = True
        uv.write_uvh5(str(flagged / f"scan_{k:03d}.uvh5"), clobber=True)
    lines = []
    summaries = run_workflow(_cfg(tmp_path / "r", str(flagged / "*.uvh5"), "mmode.min_coverage=0.5",
                                  f"mmode.coverage_policy={policy}", "transfer.noise_weighting=true"),
                             progress=False, log=lines.append)
    counts = summaries["mmodes"]["counts"]
    assert counts == {"dropped_low_coverage": int(policy == "drop"), "downweighted_low_coverage": int(policy != "drop"),
                      "baselines_without_data": 0, "fits_with_prior": 0}  # no mmode.prior_run
    assert any("low coverage: 1" in ln for ln in lines)
    g = zarr.open_group(str(tmp_path / "r" / "vis.zarr"), mode="r")
    b = [tuple(p) for p in g["pairs"][:]].index((0, 3))
    iv = zarr.open_group(str(tmp_path / "r" / "mmodes.zarr"), mode="r")["inv_var"][0]
    cross = g["pairs"][:, 0] != g["pairs"][:, 1]
    if policy == "drop":
        assert iv[b] == 0
    else:
        assert 0 < iv[b] < 0.17 * np.median(iv[cross])  # ~ coverage^2 / min_coverage of a full baseline's
