"""Shared by the tests of raw files: ingest a file as a user would, and pyuvdata's own read of it in
the store's layout."""
import numpy as np
import zarr

from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow


def ingest(path, run_dir, *extra):
    cfg = load_config("workflows/uvh5-image.yaml", [f"run.directory={run_dir}", f"input.path={path}",
                                                      "cluster.kind=synchronous", "calibrate.enabled=true", *extra])
    run_workflow(cfg, only=["ingest"], progress=False, log=lambda *a: None)
    return zarr.open_group(str(run_dir / "vis.zarr"), mode="r")


def pyuvdata_reference(path, edit=None, pols=(-5, -6)):
    """pyuvdata's read, unprojected, polarisations ``pols`` (default xx, yy; then ``edit(uv)``, e.g. a
    selection or an average), in the store's layout (integrations ascending, baselines as (i <= j) pairs of the
    antennas with data);
    flagged or non-finite samples weigh 0 (non-finite ones are stored as 0)."""
    from pyuvdata import UVData

    uv = path if isinstance(path, UVData) else UVData.from_file(str(path), run_check=False)
    if not uv._check_for_cat_type("unprojected").all():
        uv.unproject_phase()
    uv.select(polarizations=list(pols))
    uv.reorder_pols(order=[uv.polarization_array.tolist().index(p) for p in pols])
    if edit is not None:
        edit(uv)
    ants = np.unique(np.concatenate([uv.ant_1_array, uv.ant_2_array]))
    i, j = np.searchsorted(ants, uv.ant_1_array), np.searchsorted(ants, uv.ant_2_array)
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    pairs = np.unique(np.stack([lo, hi], 1), axis=0)
    times = np.unique(uv.time_array)
    t = np.searchsorted(times, uv.time_array)
    b = np.array([np.flatnonzero((pairs[:, 0] == x) & (pairs[:, 1] == y))[0] for x, y in zip(lo, hi)])
    cross = list(pols) in ([-7, -8], [-3, -4])  # V_xy(i, j) = conj(V_yx(j, i)): swapped rows trade hands
    flip = (i > j)[:, None, None]
    v = np.where(flip, np.conj(uv.data_array[:, :, [1, 0]] if cross else uv.data_array), uv.data_array)
    if cross:
        uv.flag_array = np.where(flip, uv.flag_array[:, :, [1, 0]], uv.flag_array)
        uv.nsample_array = np.where(flip, uv.nsample_array[:, :, [1, 0]], uv.nsample_array)
    vis = np.zeros((len(times), len(pairs), uv.Nfreqs, 2), complex)
    w = np.zeros(vis.shape)
    finite = np.isfinite(v)
    vis[t, b] = np.where(finite, v, 0)  # flagged samples keep their values (weight 0); non-finite ones are 0
    w[t, b] = np.where(finite & ~uv.flag_array, uv.nsample_array, 0)
    return uv, ants, pairs, vis, w
