"""Flagged time filled without settings (issue 39 item 5): ``mmode.prior_passes: auto``, the default.

A drift scan simulated by matvis (an independent simulator): three bright and six faint (5 %)
point sources seen for one sidereal day in 256 integrations by the 26 OVRO-LWA core stands within
25 m at 40 MHz, through a tabulated sin(elevation)^1.5 power beam, written as UVH5 unflagged, with
20 % of the integrations flagged in four blocks, and with 5 % flagged at random. Each is imaged by
``mmflow run``'s driver (:func:`mmflow.workflow.engine.passes.run_with_passes`) with the workflow's defaults
(lmax 64 and the scale settings of ``tests/workflow/test_gap_prior_workflow.py`` aside) and compared
with the unflagged scan's map: peak shifts in units of that map's FWHM.

Measured: least squares alone (pass 0) up to 0.106 FWHM, alm 8.3 % from the unflagged run's; the passes
change the map by 0.060, then 0.012 (< prior_tolerance 0.02): three passes, 0.015 FWHM. Unflagged and
random flags: no pass.
"""
import json

import healpy
import numpy as np
import pytest

from mmflow.analysis.peaks import measure_peak
from mmflow.conventions import radec_to_vec
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.passes import run_with_passes
from mmflow.workflow.engine.runner import stage_fingerprints
from tests.gap_helpers import DEC, FLUX, RA, flag_blocks, sin_elevation_beamfits, write_flagged
from tests.uvh5_helpers import matvis_uvdata

N_TIMES, LMAX = 256, 64
QUIET = dict(progress=False, log=lambda *a: None)




def _cfg(run_dir, data, *extra):
    """The workflow's defaults for gaps (prior_passes, prior_tolerance, min_coverage, ...), imaging (eps 0.01)
    and noise; a small lmax and map for the test's time."""
    return load_config("workflows/uvh5-image.yaml", [
        f"run.directory={run_dir}", f"input.path={data}", f"mmode.lmax={LMAX}",
        "products.nside=64", "products.png=false", "products.unit=Jy/sr", "cluster.kind=synchronous",
        "beam={type: sin_elevation, alpha: 1.5}", *extra])


def _map(run_dir):
    return healpy.read_map(str(run_dir / "maps" / "map_40.000MHz.fits"))


def _alm_error(run_dir, ref_dir):
    import zarr

    a, b = (zarr.open_group(str(d / "alm.zarr"), mode="r")["alm"][0] for d in (run_dir, ref_dir))
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def _passes(run_dir):
    return json.loads((run_dir / "prior_passes.json").read_text())


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("gap_auto")
    beam = sin_elevation_beamfits(root / "sin_el.fits")
    uv, _ = matvis_uvdata(beam, n_times=N_TIMES, radius_m=25.0, sources=tuple(zip(RA, DEC, FLUX)))
    files = {"none": write_flagged(uv, root / "none.uvh5", np.zeros(N_TIMES, bool)),
             "blocks20": write_flagged(uv, root / "blocks20.uvh5", flag_blocks(np.random.default_rng(2), N_TIMES)),
             "random5": write_flagged(uv, root / "random5.uvh5", np.random.default_rng(1).random(N_TIMES) < 0.05)}
    cfg = _cfg(root / "ref", files["none"])
    assert cfg.mmode.prior_passes == "auto"
    run_with_passes(cfg, **QUIET)
    ref = _map(root / "ref")
    vecs = [radec_to_vec(np.deg2rad(r), np.deg2rad(d)) for r, d in zip(RA, DEC)]
    return {"root": root, "files": files, "ref": ref, "vecs": vecs,
            "peaks": [measure_peak(ref, v, np.deg2rad(8)) for v in vecs]}


def _shifts(scene, hmap):
    out = []
    for v, ref in zip(scene["vecs"], scene["peaks"]):
        pk = measure_peak(hmap, v, np.deg2rad(8))
        out.append(np.arccos(np.clip(np.dot(pk["vec"], ref["vec"]), -1, 1)) / ref["fwhm_rad"])
    return np.array(out)


def test_block_flags_image_within_0p05_fwhm_of_the_unflagged_map_with_defaults(scene):
    root = scene["root"]
    summary = run_with_passes(_cfg(root / "blocks20", scene["files"]["blocks20"]), **QUIET)
    rec = _passes(root / "blocks20")
    shift = _shifts(scene, _map(root / "blocks20"))
    # the alm's distance from the unflagged run's: least squares alone (pass 0) and the final map
    err = [_alm_error(root / "blocks20" / d, root / "ref") for d in ("prior0", ".")]
    print(f"20 % in 4 blocks, defaults: {rec}; alm error pass 0 {err[0]:.4f}, final {err[1]:.4f}; "
          f"final peak shifts {shift.round(4)} FWHM")
    assert rec["baselines_with_unbridged_gaps"] > 0 and 1 < rec["passes"] <= 3
    assert summary["mmodes"]["counts"]["fits_with_prior"] > 0
    assert err[1] < 0.4 * err[0]
    assert shift.max() < 0.05


def test_unflagged_and_randomly_flagged_runs_make_no_pass_and_are_unchanged(scene, tmp_path):
    root = scene["root"]
    assert _passes(root / "ref") == {"passes": 0, "baselines_with_unbridged_gaps": 0}
    assert not (root / "ref" / "prior0").exists()
    # the default gives the run without passes bit for bit, under the same fingerprints
    zero = _cfg(tmp_path / "zero", scene["files"]["none"], "mmode.prior_passes=0")
    run_with_passes(zero, **QUIET)
    np.testing.assert_array_equal(_map(tmp_path / "zero"), scene["ref"])
    auto_fp = stage_fingerprints(_cfg(root / "ref", scene["files"]["none"]))
    zero_fp = stage_fingerprints(zero)
    assert {k: v.digest for k, v in auto_fp.items() if v} == {k: v.digest for k, v in zero_fp.items() if v}
    # ... and those of runs made before 'auto': prior_passes recorded as their 0, the new settings left out
    assert auto_fp["mmodes"].settings["mmode"]["prior_passes"] == 0
    assert not {"prior_tolerance", "prior_max_passes"} & set(auto_fp["mmodes"].settings["mmode"])
    # 5 % random flags: every gap shorter than one Nyquist interval; least squares alone, no pass
    run_with_passes(_cfg(root / "random5", scene["files"]["random5"]), **QUIET)
    assert _passes(root / "random5")["passes"] == 0 and not (root / "random5" / "prior0").exists()
    shift = _shifts(scene, _map(root / "random5"))
    print(f"5 % random, defaults: {shift.round(5)} FWHM")
    assert shift.max() < 0.01

