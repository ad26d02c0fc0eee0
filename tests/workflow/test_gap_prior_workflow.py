"""Flagged time in the workflow (issue 8 item 4): an earlier run's map as the m-mode fit's prior.

A drift scan simulated by matvis (an independent simulator): three bright and six faint (5 %)
point sources seen for one sidereal day in 384 integrations by the 15 OVRO-LWA core stands
within 18 m at 40 MHz, through a tabulated sin(elevation)^1.5 power beam, written as UVH5 with
20 % of the integrations flagged in four blocks, or 5 % at random. Each is ingested and imaged
by the workflow (lmax 48, Tikhonov eps 1e-3) and compared with the unflagged scan's map:
peak shifts in units of that map's FWHM, map difference rms over its rms. The block case is
imaged twice: least squares alone (pass 0), then again in a new run directory with
``mmode.prior_run`` = the first run (pass 1).
"""
import numpy as np
import pytest
import zarr

from mmflow.analysis.peaks import measure_peak
from mmflow.conventions import radec_to_vec
from mmflow.errors import InputError, StaleOutputError
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow, status
from tests.gap_helpers import DEC, FLUX, RA, flag_blocks, sin_elevation_beamfits, write_flagged
from tests.uvh5_helpers import matvis_uvdata

N_TIMES, LMAX = 384, 48
QUIET = dict(progress=False, log=lambda *a: None)








def _cfg(run_dir, data, *extra):
    return load_config("workflows/uvh5-image.yaml", [
        f"run.directory={run_dir}", f"input.path={data}", f"mmode.lmax={LMAX}",
        "transfer.dtype=float64", "imaging.eps=0.001", "imaging.lcurve=false", "products.nside=64",
        "products.png=false", "products.unit=Jy/sr", "cluster.kind=synchronous",
        "beam={type: sin_elevation, alpha: 1.5}", *extra])


def _map(run_dir):
    import healpy

    return healpy.read_map(str(run_dir / "maps" / "map_40.000MHz.fits"))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("gap_prior")
    beam = sin_elevation_beamfits(root / "sin_el.fits")
    uv, _ = matvis_uvdata(beam, n_times=N_TIMES, radius_m=18.0, sources=tuple(zip(RA, DEC, FLUX)))
    files = {"none": write_flagged(uv, root / "none.uvh5", np.zeros(N_TIMES, bool)),
             "blocks20": write_flagged(uv, root / "blocks20.uvh5", flag_blocks(np.random.default_rng(2), N_TIMES)),
             "random5": write_flagged(uv, root / "random5.uvh5", np.random.default_rng(1).random(N_TIMES) < 0.05)}
    run_workflow(_cfg(root / "ref", files["none"]), **QUIET)
    ref = _map(root / "ref")
    vecs = [radec_to_vec(np.deg2rad(r), np.deg2rad(d)) for r, d in zip(RA, DEC)]
    return {"root": root, "files": files, "ref": ref, "vecs": vecs,
            "peaks": [measure_peak(ref, v, np.deg2rad(8)) for v in vecs]}


def _compare(scene, hmap):
    """Peak shifts against the unflagged map's peaks (FWHM) and the map difference rms over the map rms."""
    shifts = []
    for v, ref in zip(scene["vecs"], scene["peaks"]):
        pk = measure_peak(hmap, v, np.deg2rad(8))
        shifts.append(np.arccos(np.clip(np.dot(pk["vec"], ref["vec"]), -1, 1)) / ref["fwhm_rad"])
    import healpy

    seen = scene["ref"] != healpy.UNSEEN  # the sky the array never sees
    return np.array(shifts), float(np.std((hmap - scene["ref"])[seen]) / np.std(scene["ref"][seen]))


@pytest.fixture(scope="module")
def block_passes(scene):
    """Pass 0 (least squares) and pass 1 (pass 0's map as prior) of the 20 % block-flagged scan."""
    root, data = scene["root"], scene["files"]["blocks20"]
    out = {}
    for k, extra in enumerate(([], [f"mmode.prior_run={root / 'blocks-p0'}"])):
        summary = run_workflow(_cfg(root / f"blocks-p{k}", data, *extra), **QUIET)
        out[k] = _compare(scene, _map(root / f"blocks-p{k}")) + (summary["mmodes"]["counts"]["fits_with_prior"],)
    return out


def test_block_flags_meet_the_issue_after_one_pass_with_the_first_map_as_prior(block_passes):
    (shift0, rms0, prior0), (shift1, rms1, prior1) = block_passes[0], block_passes[1]
    print(f"20 % in 4 blocks: least squares {shift0.round(3)} rms {rms0:.4f}; one pass with its map as prior "
          f"{shift1.round(3)} rms {rms1:.4f}")
    # measured: least squares faint sources up to 0.072 FWHM, map 2.8 %; one pass <= 0.021 FWHM, 1.4 %
    # (docs/mmodes.md: zero-filled 1.17 FWHM, map 88 %, on the same bins imaged by the kernels)
    assert prior0 == 0 and prior1 == 1  # the one chunk's one channel was fitted with the prior
    assert shift0.max() > 0.05  # least squares alone misses issue 8's 0.05 FWHM at this eps ...
    assert shift1.max() < 0.05  # ... one pass meets it
    assert shift1[3:].max() < 0.6 * shift0[3:].max() and rms1 < 0.75 * rms0


def test_random_flags_are_within_the_issue_without_a_prior(scene):
    root = scene["root"]
    run_workflow(_cfg(root / "random5", scene["files"]["random5"]), **QUIET)
    shift, rms = _compare(scene, _map(root / "random5"))
    print(f"5 % random: least squares {shift.round(4)} rms {rms:.2e}")
    # measured: <= 1e-4 FWHM, map 1e-5
    assert shift.max() < 0.03 and rms < 1e-3


def test_refit_prior_m0_gives_the_data_m0_beside_the_map_model():
    """Band-limited data with gaps: a prior holding the true m != 0 and a wrong m = 0 gets the true m = 0."""
    from mmflow.mmode.gapfill import refit_prior_m0

    rng = np.random.default_rng(3)
    n, k, nbl = 96, 12, 4
    true = rng.normal(size=(k + 1, 2, nbl)) + 1j * rng.normal(size=(k + 1, 2, nbl))
    true[0, 1] = 0
    for offset in (np.zeros(n), rng.uniform(-0.02, 0.02, n)):
        phi = 2 * np.pi * np.arange(n) / n + offset
        # V_n = sum_m V_m e^{i m phi_n}, V_{-m} = conj(layout[m, 1]), written out independently of the kernels
        vis = sum(true[m, 0][None, :] * np.exp(1j * m * phi)[:, None] for m in range(k + 1))
        vis = vis + sum(np.conj(true[m, 1])[None, :] * np.exp(-1j * m * phi)[:, None] for m in range(1, k + 1))
        w = rng.uniform(0.5, 2.0, (n, nbl)) * (rng.random((n, nbl)) > 0.2)
        w[30:45] = 0  # a gap
        prior = true.copy()
        prior[0, 0] = 0  # what a map with m = 0 filtered predicts
        out = refit_prior_m0(prior, vis, w, offset)
        np.testing.assert_allclose(out[0, 0], true[0, 0], atol=1e-10)
        np.testing.assert_array_equal(out[1:], true[1:])


def test_prior_run_refused_before_any_work(scene, tmp_path):
    root = scene["root"]
    ref = root / "ref"
    cases = {  # (overrides, words the message must hold)
        "lmax": (["mmode.lmax=40"], "lmax 48"),
        "itself": ([f"run.directory={ref}"], "own directory"),
        "missing": ([f"mmode.prior_run={tmp_path / 'nowhere'}"], "no such run directory"),
    }
    for name, (extra, words) in cases.items():
        args = [f"run.directory={tmp_path / name}", f"mmode.prior_run={ref}", *extra]
        with pytest.raises(InputError) as err:
            _cfg(tmp_path / name, scene["files"]["blocks20"], *args)
        assert err.value.field == "mmode.prior_run" and words in str(err.value), (name, str(err.value))
        assert not (tmp_path / name).exists()
    # simulated data: channels and epoch are known from the configuration
    sim = ["telescope.radius_m=18", "observation.integration_s=224.3856", f"mmode.lmax={LMAX}",
           "cluster.kind=synchronous", f"mmode.prior_run={ref}"]
    for extra, words in ((["observation.freqs_mhz=[50.0]"], "channels"),
                         (["observation.freqs_mhz=[40.0]", "observation.epoch_jd=2460000.5"], "epoch")):
        with pytest.raises(InputError, match=words):
            load_config("workflows/demo.yaml", sim + extra + [f"run.directory={tmp_path / 'sim'}"])
        assert not (tmp_path / "sim").exists()
    # ingested data: the mmodes stage compares the channels and epoch in its prepare, before any task
    import shutil

    other = tmp_path / "other-epoch"
    shutil.copytree(ref, other)
    zarr.open_group(str(other / "vis.zarr"), mode="r+").attrs["epoch_jd"] = 2460000.5
    with pytest.raises(InputError, match="epoch") as err:
        run_workflow(_cfg(tmp_path / "p1", scene["files"]["blocks20"], f"mmode.prior_run={other}"), **QUIET)
    assert err.value.field == "mmode.prior_run"
    assert (tmp_path / "p1" / "vis.zarr").exists() and not (tmp_path / "p1" / "mmodes.zarr").exists()


class Crash(BaseException):
    """Stands for a kill (nothing after it runs; the run's lock goes with the exception)."""


def test_prior_pass_inside_one_run_equals_the_two_run_recipe_and_resumes_bit_identical(scene, block_passes,
                                                                                      tmp_path, monkeypatch):
    """``mmode.prior_passes=1``: one run gives the second run's map of the two-run recipe bit for bit (and so
    meets the 0.05 FWHM the recipe meets); a run killed inside the pass's transfer stage resumes to it."""
    from mmflow.workflow.engine.passes import run_with_passes
    from mmflow.workflow.engine.rundir import RunDir

    root, data = scene["root"], scene["files"]["blocks20"]
    one = tmp_path / "one"
    summary = run_with_passes(_cfg(one, data, "mmode.prior_passes=1"), **QUIET)
    assert summary["mmodes"]["counts"]["fits_with_prior"] == 1 and "prior0/solve" in summary
    assert (one / "prior0" / "vis.zarr").is_symlink() and not (one / "prior0" / "_status" / "ingest").resolve() \
        .is_relative_to(one / "prior0")  # the calibration stages' stores and records are shared, not redone
    np.testing.assert_array_equal(_map(one), _map(root / "blocks-p1"))
    shift, _ = _compare(scene, _map(one))
    assert shift.max() < 0.05

    killed = tmp_path / "killed"
    real = RunDir.mark_done
    count = {"n": 0}

    def die_in_the_pass(self, stage, key, info, chunks):
        real(self, stage, key, info, chunks)
        if stage == "transfer" and self.path.name == "prior0" and not key.startswith("_"):
            count["n"] += 1
            if count["n"] == 2:
                raise Crash()

    monkeypatch.setattr(RunDir, "mark_done", die_in_the_pass)
    with pytest.raises(Crash):
        run_with_passes(_cfg(killed, data, "mmode.prior_passes=1"), **QUIET)
    monkeypatch.undo()
    assert not (killed / "alm.zarr").exists()
    run_with_passes(_cfg(killed, data, "mmode.prior_passes=1"), **QUIET)
    np.testing.assert_array_equal(_map(killed), _map(one))
    for store in ("alm.zarr", "prior0/alm.zarr"):
        a = zarr.open_group(str(killed / store), mode="r")["alm"][:]
        np.testing.assert_array_equal(a, zarr.open_group(str(one / store), mode="r")["alm"][:])


def test_prior_passes_and_prior_run_together_are_refused(scene, tmp_path):
    with pytest.raises(InputError, match="prior_passes and mmode.prior_run"):
        _cfg(tmp_path / "x", scene["files"]["blocks20"], "mmode.prior_passes=1",
             f"mmode.prior_run={scene['root'] / 'ref'}")


def test_recomputed_prior_run_makes_the_pass_stale(scene, block_passes):
    """Runs last: it changes the block passes' runs."""
    root, data = scene["root"], scene["files"]["blocks20"]
    p0, p1 = root / "blocks-p0", root / "blocks-p1"
    cfg1 = _cfg(p1, data, f"mmode.prior_run={p0}")
    # a setting of the earlier run that leaves its alm alone does not touch the pass
    run_workflow(_cfg(p0, data, "products.nside=32"), force=True, **QUIET)
    assert not any(s and s["stale"] for s in status(p1).values())
    run_workflow(cfg1, **QUIET)
    # the earlier run recomputed with another eps: its alm changed, so the pass's mmodes and all after are stale
    run_workflow(_cfg(p0, data, "imaging.eps=0.01"), force=True, **QUIET)
    st = status(p1)
    assert not st["ingest"]["stale"]
    assert all(st[s]["stale"] for s in ("mmodes", "transfer", "normal", "solve", "products"))
    with pytest.raises(StaleOutputError, match="alm.zarr/alm changed"):
        run_workflow(cfg1, **QUIET)
    before = zarr.open_group(str(p1 / "alm.zarr"), mode="r")["alm"][:]
    summary = run_workflow(cfg1, force=True, **QUIET)
    assert summary["mmodes"]["tasks_run"] == 1 and summary["ingest"]["tasks_run"] == 0
    assert not any(s and s["stale"] for s in status(p1).values())
    assert not np.array_equal(zarr.open_group(str(p1 / "alm.zarr"), mode="r")["alm"][:], before)
