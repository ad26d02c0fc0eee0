"""The simulate stage's diffuse sky: summed at N = 2 L + 1 + margin sidereal angles (its first phase,
``diffuse.zarr``) and interpolated to every integration of the time chunks (mmflow.simulate.drift_modes);
the same visibilities as the direct sum at every integration, to the quadrature's residue."""
import numpy as np
import pytest
import zarr

from mmflow.simulate.drift_modes import n_samples
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import small_config

QUIET = dict(progress=False, log=lambda *a: None)


# 50 integrations: the direct full-Stokes sum of the diffuse sky at every integration is the slow reference
FULL_STOKES = ("imaging.stokes=[I, Q, U, V]", "beam={type: short_dipole, horizon_taper: 3}",
               "observation.integration_s=1723.281724")


@pytest.mark.parametrize("stokes", [(), FULL_STOKES], ids=["stokes-i", "full-stokes"])
def test_interpolated_diffuse_sky_equals_the_direct_sum(tmp_path, monkeypatch, stokes):
    """Also the four correlations of a full-Stokes simulation (the diffuse sky through the E-field beam,
    its samples summed by ``herk`` in single precision; the direct path sums it in double)."""
    extra = ("sky.noise=false", "sky.sources=[\"Cyg A\"]") + stokes
    cfg = small_config(tmp_path / "interp", *extra, "run.keep=[diffuse.zarr]")  # else released after simulate
    run_workflow(cfg, only=("simulate",), **QUIET)
    d = zarr.open_group(str(tmp_path / "interp" / "diffuse.zarr"), mode="r")
    assert d["samples"].shape[:2] == (1, n_samples(cfg.sky.diffuse_lmax))
    monkeypatch.setattr("mmflow.workflow.stages.simulate.stage.interpolates_diffuse", lambda cfg: False)
    run_workflow(small_config(tmp_path / "direct", *extra), only=("simulate",), **QUIET)
    assert not (tmp_path / "direct" / "diffuse.zarr").exists()
    names = ("vis", "vis_cross") if stokes else ("vis",)
    a = np.concatenate([zarr.open_group(str(tmp_path / "interp" / "vis.zarr"), mode="r")[n][:] for n in names])
    b = np.concatenate([zarr.open_group(str(tmp_path / "direct" / "vis.zarr"), mode="r")[n][:] for n in names])
    assert a.shape == b.shape and np.abs(b).max() > 0
    # the direct path sums the sky in single precision (simulate_chunk): its rounding, ~1.7e-5 of the
    # largest visibility here, bounds the difference; the interpolation's own residue is ~1e-6
    # (tests/unit/simulate/test_drift_modes.py, against a double-precision direct sum)
    assert np.abs(a - b).max() < 5e-5 * np.abs(b).max()
