"""Read one MeasurementSet's rows directly with python-casacore (an ingest task's step).

The plan has read and checked every file's metadata (``mmflow.io.ms_index``: one spectral
window, the antenna table, correlation types, units, sidereal phase centres), so a task needs
only the main table's columns. pyuvdata's MS reader re-reads
every subtable and computes apparent coordinates per file, which costs as much as the data.
This reader reproduces what ``UVData.read`` followed by ``unproject_phase`` gives (pyuvdata
docs, "MeasurementSet"; ``tests/workflow/test_ingest_formats.py`` compares the stores to the UVH5 path):

* conjugation: an MS stores ``V_21`` where pyuvdata stores ``V_12``; pyuvdata conjugates
  ``DATA`` and negates ``UVW`` unless the file says it was written in pyuvdata's convention
  (the main table's ``pyuvdata_flip_conj`` keyword, else a ``pyuvdata`` entry in ``HISTORY``);
* times as the plan converts them (:func:`mmflow.io.ms_index.ms_time_to_jd`); LSTs the
  site's apparent sidereal time at those times (:func:`mmflow.sky.frames.apparent_sidereal_time`,
  pyuvdata's ``get_lst_for_time``);
* weights ``WEIGHT_SPECTRUM``, else ``WEIGHT`` repeated over channels;
* phased rows (any phase centre) unprojected to a drift scan as ``unproject_phase`` does: new w = 0,
  ``V *= exp(-2 pi i (0 - w) nu / c)`` with ``w`` pyuvdata's (sign-flipped) ``UVW[:, 2]``,
  in the same order of operations, in the column's precision;
* autocorrelations' parallel hands made real, as the UVH5 reader does (cross hands stay complex).
"""
from __future__ import annotations

from contextlib import nullcontext

import numpy as np

from mmflow.io.file_data import FileData
from mmflow.io.ms_index import ms_time_to_jd
from mmflow.io.polarization import select_pols
from mmflow.sky.frames import apparent_sidereal_time
from mmflow.conventions import SPEED_OF_LIGHT



def read_ms_direct(path, pol_numbers, phased, site, lock=None, n_parallel=None):
    """A :class:`mmflow.io.file_data.FileData` of one MS's kept polarisations.

    Parameters
    ----------
    pol_numbers : list of int
        pyuvdata (AIPS) numbers of the polarisations to keep, in order; found in the MS's own
        ``POLARIZATION.CORR_TYPE`` order (pyuvdata reorders it, e.g. CASA's XX, XY, YX, YY to
        XX, YY, XY, YX).
    phased : bool
        The plan found the file phased (to any phase centre): unproject it.
    site : (lat_deg, lon_deg, height_m)
        Where the LSTs are computed (the plan's checked layout).
    lock : threading.Lock, optional
        Held while casacore reads (its table cache is not thread-safe).
    n_parallel : int, optional
        How many of ``pol_numbers`` (the first) are parallel hands, made real in autocorrelations
        (default: all).
    """
    # deferred: optional (python-casacore); pyuvdata takes 2-3.5 s to import (docs/performance.md)
    from casacore.tables import table
    from pyuvdata.utils.io.ms import POL_CASA2AIPS_DICT

    p = str(path).rstrip("/")
    with lock or nullcontext():
        with table(p, ack=False, readonly=True) as t:
            flip = t.getkeywords().get("pyuvdata_flip_conj", None)
            time_s = t.getcol("TIME")
            scale = t.getcolkeyword("TIME", "MEASINFO")["Ref"]
            ant1, ant2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
            uvw = t.getcol("UVW")
            data = t.getcol("DATA")
            flags = t.getcol("FLAG")
            try:
                nsample = t.getcol("WEIGHT_SPECTRUM")
            except RuntimeError:
                nsample = np.repeat(t.getcol("WEIGHT")[:, None, :], data.shape[1], axis=1)
        with table(p + "/SPECTRAL_WINDOW", ack=False, readonly=True) as t:
            freqs = np.asarray(t.getcol("CHAN_FREQ"), float).ravel()
        with table(p + "/POLARIZATION", ack=False, readonly=True) as t:
            corr = [POL_CASA2AIPS_DICT[int(c)] for c in np.ravel(t.getcol("CORR_TYPE")[0])]
        if flip is None:
            with table(p + "/HISTORY", ack=False, readonly=True) as t:
                apps = t.getcol("APPLICATION") if t.nrows() > 0 else []
            flip = not any("pyuvdata" in a for a in apps)
    if flip:
        data = np.conj(data)
        uvw = -uvw
    if phased:
        delta_w = (0.0 - np.asarray(uvw[:, 2], np.float64)).reshape(-1, 1)
        delta_w_lambda = delta_w * (1.0 / SPEED_OF_LIGHT) * freqs.reshape(1, -1)
        data *= np.exp((-1j * 2 * np.pi) * delta_w_lambda[:, :, None])
    time_jd = ms_time_to_jd(time_s, scale)
    lon = site[1]
    lst = apparent_sidereal_time(time_jd, lon)
    vis, flg, ns = select_pols(data, flags, np.asarray(nsample, float), [corr.index(int(n)) for n in pol_numbers])
    auto = ant1 == ant2
    if auto.any():
        vis[auto, :, :n_parallel] = vis[auto, :, :n_parallel].real
    return FileData(time_jd, ant1, ant2, lst, vis, flg, ns, freqs)
