"""A simulated drift scan written as the files a telescope writes (``observation.raw_files``).

The simulate stage can write each time chunk of its visibilities as one UVH5 file, so that a run with
``source: ingest`` reads them through the path real data take (pyuvdata's file format, the ingest
plan's checks, LSTs recomputed from the files' UTC times, the flux convention of the file's
``pol_convention``). The file for the integrations ``t0 .. t1 - 1`` is ``raw/t{t0:06d}.uvh5``; it
holds every baseline and channel of those integrations, the parallel hands XX, YY (and the cross
hands XY, YX of a full-Stokes simulation), with the simulator's ``pol_convention="avg"``
(``I = (XX + YY) / 2``) and the data's sign convention (``V_ij ~ exp(+2 pi i (x_j - x_i).r / lambda)``,
pyuvdata's: ingest with ``conjugate: false``), the data in single precision. Each file is written
under a temporary name and renamed, so a killed task leaves no partial file under the final name.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: the folder of the run directory that holds the files
RAW_DIR = "raw"


def raw_path(run_path, t0):
    """The UVH5 file of the integrations from ``t0`` in the run directory ``run_path``."""
    return Path(run_path) / RAW_DIR / f"t{int(t0):06d}.uvh5"


def write_raw_chunk(path, telescope, vis, weights, pairs, times_jd, freqs_hz, pols, integration_s,
                    channel_width_hz):
    """Write (time, bl, freq, pol) visibilities of ``pairs`` at ``times_jd`` as one UVH5 file at ``path``.

    ``pols``: the names of the last axis (``xx``, ``yy``, ``xy``, ``yx``). Weights of 0 become
    flags. Written to a hidden sibling and renamed onto ``path``; returns ``path``.
    """
    from mmflow.simulate.corrupt import to_uvdata  # deferred: pyuvdata takes 2-3.5 s to import

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    uv = to_uvdata(vis, weights, pairs, telescope, np.asarray(times_jd, float), np.asarray(freqs_hz, float),
                   pols=tuple(pols), channel_width_hz=channel_width_hz, integration_s=integration_s,
                   pol_convention="avg")
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    # single precision on disk, as a correlator writes it (the simulation is complex64: nothing lost)
    uv.write_uvh5(str(tmp), clobber=True, run_check=False, data_write_dtype="c8")
    os.replace(tmp, path)
    return path
