"""Ingest refuses or converts what it must not trust: polarisation labels (by number), phased data,
units, antenna positions and site, duplicated rows, unflagged NaN/inf. Data: matvis through pyuvdata,
recorded in 2023, two linear polarisations with different gains and flags."""
import os
from types import SimpleNamespace

import numpy as np
import pytest
import zarr

from mmflow.errors import InputError
from mmflow.io.ingest import ingest_time_chunk
from mmflow.io.polarization import stokes_i_recipe
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.engine.runner import run_workflow
from tests.uvh5_helpers import JD_2023, gaussian_power_beamfits, matvis_uvdata

YY_GAIN = 0.9


@pytest.fixture(scope="module")
def uv(tmp_path_factory):
    root = tmp_path_factory.mktemp("checks")
    beam = gaussian_power_beamfits(root / "beam.fits")
    uv, _ = matvis_uvdata(beam, n_times=8, radius_m=12.0, start_jd=JD_2023, pols=("xx", "yy"), yy_gain=YY_GAIN,
                          flag_fraction=0.05, seed=3)
    return uv


def ingest(run_dir, pattern, *extra):
    cfg = load_config("workflows/uvh5-image.yaml", [f"run.directory={run_dir}", f"input.path={pattern}",
                                                      "cluster.kind=synchronous", *extra])
    run_workflow(cfg, only=["ingest"], progress=False, log=lambda *a: None)
    return zarr.open_group(str(run_dir / "vis.zarr"), mode="r")


def write(uv, path, **kw):
    path.parent.mkdir(parents=True, exist_ok=True)
    uv.write_uvh5(str(path), clobber=True, **kw)
    return path


def expected_stokes_i(uv):
    """(XX + YY) / 2 per (time, baseline) in the store's order (times ascending, baselines i <= j), in
    mmflow's 'avg' convention: a file in pyuvdata's 'sum' convention (matvis) counts twice."""
    xx = uv.data_array[:, 0, 0].reshape(uv.Ntimes, uv.Nbls)
    flags = np.any(uv.flag_array[:, 0, :], axis=-1).reshape(uv.Ntimes, uv.Nbls)
    factor = 2.0 if uv.pol_convention == "sum" else 1.0
    return factor * (1 + YY_GAIN) / 2 * xx, flags


@pytest.fixture(scope="module")
def reference(uv, tmp_path_factory):
    root = tmp_path_factory.mktemp("ref")
    return ingest(root / "run", str(write(uv, root / "in" / "xxyy.uvh5")))


def test_stokes_i_recipe_by_number():
    assert stokes_i_recipe([-5, -6]) == ((0, 1), False)
    assert stokes_i_recipe([-5, -7, -8, -6]) == ((0, 3), False)  # 4-pol: XX and YY
    assert stokes_i_recipe([-6, -5]) == ((1, 0), False)
    assert stokes_i_recipe([1]) == ((0,), False)  # I and pseudo-Stokes pI share number 1
    assert stokes_i_recipe([-1, -2, -3, -4]) == ((0, 1), False)  # circular: (RR + LL) / 2
    assert stokes_i_recipe([-5]) == ((0,), True)  # one parallel hand stands in for I
    for cross in ([-7], [-8], [-7, -8], [-3, -4], [2, 3]):
        with pytest.raises(InputError, match="polarization_array.*cannot form Stokes I"):
            stokes_i_recipe(cross, "f.uvh5")


def _stokes_i(g):
    """Stokes I of a vis.zarr (the mmodes stage forms it after calibration, on read)."""
    from mmflow.io.polarization import stokes_i

    return stokes_i(g["vis"][:], g["weights"][:])


def test_xx_yy_is_their_mean_flagged_where_either_is(uv, reference):
    vis, flags = expected_stokes_i(uv)
    pairs = reference["pairs"][:]
    assert np.all(pairs[:, 0] <= pairs[:, 1]) and len(pairs) == uv.Nbls
    assert reference.attrs["pols"] == ["xx", "yy"]
    got, w = _stokes_i(reference)
    got, w = got[:, :, 0], w[:, :, 0]
    assert np.array_equal(w == 0, flags) and flags.any()
    F32 = np.finfo(np.float32).eps  # each hand is stored in float32, then averaged
    np.testing.assert_allclose(got[~flags], vis[~flags], rtol=0, atol=4 * F32 * np.abs(vis).max())


def test_ee_nn_four_pol_and_pseudo_stokes_give_the_same_stokes_i(uv, reference, tmp_path):
    from pyuvdata import UVData

    east = uv.copy()
    east.telescope.set_feeds_from_x_orientation("east")
    p = write(east, tmp_path / "ee" / "eenn.uvh5")
    assert UVData.from_file(str(p), read_data=False).get_pols() == ["ee", "nn"]
    four = uv.copy()
    rng = np.random.default_rng(1)
    cross = rng.normal(size=(uv.Nblts, 1, 2)) + 1j * rng.normal(size=(uv.Nblts, 1, 2))
    four.data_array = np.concatenate([uv.data_array[..., :1], cross, uv.data_array[..., 1:]], axis=-1)
    four.flag_array = np.concatenate([uv.flag_array[..., :1], np.zeros((uv.Nblts, 1, 2), bool),
                                      uv.flag_array[..., 1:]], axis=-1)
    four.nsample_array = np.ones(four.data_array.shape, np.float32)
    four.polarization_array = np.array([-5, -7, -8, -6])
    four.Npols = 4
    four._fix_autos()
    pseudo = uv.select(polarizations=[-5], inplace=False)
    pseudo.data_array = 0.5 * (uv.data_array[..., :1] + uv.data_array[..., 1:])
    pseudo.flag_array = np.any(uv.flag_array, axis=-1, keepdims=True)
    pseudo.polarization_array = np.array([1])  # pI
    for name, obj in (("eenn", east), ("fourpol", four), ("pI", pseudo)):
        g = ingest(tmp_path / f"run_{name}", str(write(obj, tmp_path / name / f"{name}.uvh5", fix_autos=True)))
        assert g.attrs["pols"] == (["I"] if name == "pI" else ["xx", "yy"])
        vis, w = _stokes_i(g)
        ref_vis, ref_w = _stokes_i(reference)
        np.testing.assert_array_equal(w, ref_w, err_msg=name)
        np.testing.assert_allclose(vis, ref_vis, rtol=0, atol=4 * np.finfo(np.float32).eps * np.abs(ref_vis).max(),
                                   err_msg=name)


def test_cross_hands_alone_are_refused(uv, tmp_path):
    xy = uv.copy()
    xy.polarization_array = np.array([-7, -8])
    p = write(xy, tmp_path / "xy" / "crossonly.uvh5", run_check=False)
    with pytest.raises(InputError, match=r"crossonly.uvh5.*polarization_array.*\['XY', 'YX'\]"):
        ingest(tmp_path / "run", str(p))
    one = uv.select(polarizations=[-5], inplace=False)
    one.polarization_array = np.array([-7])
    p = write(one, tmp_path / "xy1" / "xyonly.uvh5", run_check=False)
    with pytest.raises(InputError, match=r"xyonly.uvh5.*polarization_array"):
        ingest(tmp_path / "run1", str(p))


def test_phased_data_unprojected_exactly_any_phase_centre(uv, reference, tmp_path):
    """A file phased to a fixed sidereal centre (many integrations) and one file per integration phased
    to its own zenith (as MeasurementSets are) are unprojected as pyuvdata's unproject_phase does:
    the store equals the drift scan's."""
    phased = uv.copy()
    phased.phase(ra=1.0, dec=0.5, cat_name="tracked")
    g = ingest(tmp_path / "run", str(write(phased, tmp_path / "ph" / "tracked.uvh5")))
    ref = reference["vis"][:]
    np.testing.assert_array_equal(g["weights"][:], reference["weights"][:])
    assert np.max(np.abs(g["vis"][:] - ref)) <= 4 * np.finfo(np.float32).eps * np.max(np.abs(ref))
    d = tmp_path / "snap"
    for k, t in enumerate(np.unique(uv.time_array)):
        part = uv.select(times=[t], inplace=False)
        part.phase_to_time(t)
        write(part, d / f"snap_{k}.uvh5")
    g = ingest(tmp_path / "run_snap", str(d / "*.uvh5"))
    np.testing.assert_array_equal(g["weights"][:], reference["weights"][:])
    assert np.max(np.abs(g["vis"][:] - ref)) <= 4 * np.finfo(np.float32).eps * np.max(np.abs(ref))


def test_units_uncalibrated_refused_kelvin_steradian_converted(uv, reference, tmp_path):
    bad = uv.copy()
    bad.vis_units, bad.pol_convention = "uncalib", None  # pyuvdata: uncalibrated data have no convention
    with pytest.raises(InputError, match=r"raw.uvh5.*vis_units.*uncalibrated.*calibrate.enabled=true"):
        ingest(tmp_path / "run", str(write(bad, tmp_path / "u" / "raw.uvh5")))
    g = ingest(tmp_path / "run_u", str(write(bad, tmp_path / "u" / "raw.uvh5")), "calibrate.enabled=true")
    # kept as they are (the gains set the scale), where the reference, in matvis's 'sum' convention, was doubled
    np.testing.assert_array_equal(g["vis"][:], reference["vis"][:] / 2)
    ksr = uv.copy()
    ksr.vis_units = "K str"
    g = ingest(tmp_path / "run_k", str(write(ksr, tmp_path / "k" / "ksr.uvh5")))
    jy_per_ksr = 2 * 1.380649e-23 * 40e6**2 / 299792458.0**2 * 1e26  # Rayleigh-Jeans, written out here
    ref = reference["vis"][:]
    np.testing.assert_allclose(g["vis"][:], ref * jy_per_ksr, rtol=1e-6, atol=1e-6 * np.abs(ref).max() * jy_per_ksr)


def test_antenna_positions_and_site_compared_across_files(uv, tmp_path):
    times = np.unique(uv.time_array)
    a, b = uv.select(times=times[:4], inplace=False), uv.select(times=times[4:], inplace=False)
    d = tmp_path / "pos"
    write(a, d / "a.uvh5")
    moved = b.copy()
    moved.telescope.antenna_positions[3] += [0.0, 0.05, 0.0]
    write(moved, d / "b.uvh5", run_check=False)
    with pytest.raises(InputError, match=r"b.uvh5.*antenna_positions.*antenna 3 is 0.050 m from its position in .*a.uvh5"):
        ingest(tmp_path / "run", str(d / "*.uvh5"))
    site = b.copy()
    site.telescope.location = site.telescope.location.__class__.from_geocentric(
        *(np.asarray(site.telescope._location.xyz()) + [1.0, 0.0, 0.0]), unit="m")
    write(site, d / "b.uvh5", run_check=False)
    with pytest.raises(InputError, match=r"b.uvh5.*telescope.location.*1.000 m"):
        ingest(tmp_path / "run1", str(d / "*.uvh5"))


def test_duplicated_time_baseline_rows_named(uv, tmp_path):
    dup = uv.copy()
    t0 = dup.time_array == dup.time_array[0]
    rows = np.flatnonzero(t0)
    q, r = rows[1], rows[2]  # make row r the (reversed) baseline of row q at the same time
    dup.ant_1_array[r], dup.ant_2_array[r] = dup.ant_2_array[q], dup.ant_1_array[q]
    dup.baseline_array = dup.antnums_to_baseline(dup.ant_1_array, dup.ant_2_array)
    p = write(dup, tmp_path / "d" / "dup.uvh5", run_check=False)
    with pytest.raises(InputError, match=rf"dup.uvh5.*1 duplicated \(time, baseline\) rows: rows {q} and {r}"):
        ingest(tmp_path / "run", str(p))


def test_unflagged_nonfinite_refused_before_writing_or_flagged_and_counted(uv, tmp_path):
    bad = uv.copy()
    bad.flag_array[:] = False
    bad.data_array[5, 0, 0] = np.nan
    bad.data_array[9, 0, 1] = np.inf
    bad.data_array[12, 0, 0] = np.nan
    bad.flag_array[12, 0, 0] = True  # a flagged NaN: allowed (each hand is kept, so its own flag counts)
    p = write(bad, tmp_path / "nan" / "nonfinite.uvh5", run_check=False)
    run_dir = tmp_path / "run"
    with pytest.raises(InputError, match=r"nonfinite.uvh5.*data_array.*2 unflagged samples are NaN or inf.*nonfinite=flag"):
        ingest(run_dir, str(p))
    assert sorted(os.listdir(run_dir)) == ["mmflow.log"]  # refused by the plan's scan: no store, no record
    g = ingest(run_dir, str(p), "input.nonfinite=flag")  # the fix, without --force
    assert RunDir(run_dir).completion("ingest")["counts"]["nonfinite_flagged"] == 2
    v, w = _stokes_i(g)
    w, v = w[:, :, 0].ravel(), v[:, :, 0].ravel()  # rows in file order here
    assert np.all(np.isfinite(v)) and list(np.flatnonzero(w == 0)) == [5, 9, 12]
    # a task checks the same samples, and refuses before it writes (formats the plan cannot scan: uvfits)
    before = g["vis"][:]
    cfg = SimpleNamespace(input=SimpleNamespace(format=None, conjugate=False, nonfinite="error"))
    with pytest.raises(InputError, match=r"nonfinite.uvh5.*2 unflagged samples are NaN or inf"):
        ingest_time_chunk(cfg, run_dir / "vis.zarr", 0, 256)
    assert np.array_equal(g["vis"][:], before)


def test_uvh5_plan_reads_one_file_with_pyuvdata_the_rest_with_h5py_and_checks_each(uv, tmp_path):
    """Many UVH5 files: the plan's h5py pass gives pyuvdata's plan and refuses what pyuvdata's would."""
    import shutil

    import h5py

    from mmflow.io import ingest
    from mmflow.io.uvh5_index import UVH5Index

    d = tmp_path / "uvh5"
    for k, t in enumerate(np.unique(uv.time_array)[:5]):
        write(uv.select(times=[t], inplace=False), d / f"int_{k}.uvh5")
    files = [str(p) for p in sorted(d.glob("*.uvh5"))]
    fast = ingest._metadata_indexed(files, None, "error", "uvh5")
    assert fast is not None and all(isinstance(m, UVH5Index) for m in fast[0][1:])
    slow = ingest._metadata_pyuvdata(files, None, "error")
    assert fast[1] == slow[1] and fast[3] == slow[3]
    for a, b in zip(fast[0][1:], slow[0][1:]):  # compacted: the file's distinct times and antenna pairs
        assert a.compact
        np.testing.assert_array_equal(a.time_array, np.unique(b.time_array))
        pairs = np.unique(np.stack([b.ant_1_array, b.ant_2_array], 1), axis=0)
        np.testing.assert_array_equal(np.stack([a.ant_1_array, a.ant_2_array], 1), pairs)

    def refused(match, edit, name):
        bad = tmp_path / name
        shutil.copytree(d, bad)
        with h5py.File(bad / "int_3.uvh5", "r+") as f:
            edit(f["Header"])
        ingest._plan.cache_clear()
        with pytest.raises(InputError, match=match):
            ingest._plan(str(bad / "*.uvh5"), None, "error")

    def move_antenna(h):
        h["antenna_positions"][2, 1] += 0.05

    def move_site(h):
        h["altitude"][()] = h["altitude"][()] + 1.0

    def cross_pols(h):
        h["polarization_array"][:] = [-7, -8]

    def uncalibrated(h):
        del h["vis_units"]
        h["vis_units"] = np.bytes_("uncalib")

    def phased(h):
        for k in h["phase_center_catalog"]:
            del h["phase_center_catalog"][k]["cat_type"]
            h["phase_center_catalog"][k]["cat_type"] = np.bytes_("sidereal")

    def duplicate_row(h):
        h["ant_2_array"][2] = h["ant_2_array"][1]
        h["ant_1_array"][2] = h["ant_1_array"][1]

    refused(r"int_3.uvh5.*antenna_positions.*antenna 2 is 0.050 m", move_antenna, "moved")
    refused(r"int_3.uvh5.*telescope.location.*1.000 m", move_site, "site")
    refused(r"int_3.uvh5.*polarization_array.*\[-7, -8\] differ", cross_pols, "pols")
    refused(r"int_3.uvh5.*vis_units.*'uncalib'", uncalibrated, "uncal")
    refused(r"int_3.uvh5.*phase_center_catalog \(cat_type=sidereal\).*unproject_phase", phased, "phased")
    refused(r"int_3.uvh5.*duplicated \(time, baseline\) rows: rows 1 and 2", duplicate_row, "dup")
    ingest._plan.cache_clear()  # a readable file with repeated rows is refused as that, never skipped as unreadable
    with pytest.raises(InputError) as info:
        ingest._plan(str(tmp_path / "dup" / "*.uvh5"), None, "skip")
    assert "duplicated" in str(info.value) and "cannot read" not in str(info.value)
