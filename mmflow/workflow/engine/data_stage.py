"""What the two data stages (``simulate`` and ``ingest``) share: the arrays of ``vis.zarr`` they write
per time chunk, the array's layout as store attributes, and the autocorrelation rows.

Both write ``vis.zarr`` (declared in :mod:`mmflow.io.run_stores`); only one runs in a workflow.
"""
from __future__ import annotations

from mmflow.io.run_stores import STORES
from mmflow.mmode.noise import autocorrelation_rows

#: the arrays of ``vis.zarr`` written row by row per time chunk
VIS_ARRAYS = (STORES.vis.vis, STORES.vis.weights, STORES.vis.lst, STORES.vis.time_jd)


def write_autos(ctx, g, rows, vis, weights):
    """Write the ``autos`` rows of ``vis.zarr`` (``|V_ii|`` per antenna, NaN where unmeasured) from a
    time chunk's visibilities (:func:`mmflow.mmode.noise.autocorrelation_rows`)."""
    n_ant = g[STORES.vis.autos].shape[1]
    ctx.write(g, STORES.vis.autos, rows, autocorrelation_rows(vis, weights, g[STORES.vis.pairs][:], n_ant),
              allow_nan=True)


def layout_attrs(layout):
    """Store attributes of an array layout: antenna names, site (deg, m) and the layout's provenance."""
    return dict(antenna_names=list(layout.names), lat_deg=layout.lat_deg, lon_deg=layout.lon_deg,
                height_m=layout.height_m, layout_provenance=layout.provenance)
