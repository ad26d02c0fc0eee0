"""The ``stokes`` stage: full-Stokes imaging (``imaging.stokes: [I, Q, U, V]``), one task per frequency.

Each task reads the m-modes of the four correlations (``mmodes.zarr``'s ``mmodes_corr``, xx, yy,
xy, yx), builds the full-Stokes transfer coefficients of every baseline through the E-field beam
(:func:`mmflow.mmode.polarised.polarised_transfer_blocks`, the beam from ``beam``: type
``short_dipole`` or a pyuvdata E-field beam), accumulates ``G_m = B_m^H W B_m`` and
``r_m = B_m^H W v_m`` over the ``4 (lmax - m + 1)`` unknowns ``[T; E; B; V]``
(:func:`mmflow.imaging.polarised.accumulate_polarised_normal`, ``W`` the correlations' relative
inverse noise variances where ``transfer.noise_weighting``) and solves
``x_m = (G_m + D)^-1 r_m`` with ``D = diag(eps, eps_pol, eps_pol, eps_pol)`` and the Stokes-I
solve's m-filters (:func:`mmflow.imaging.polarised.solve_polarised`). It also writes the
leakage: the image through the same solve of the unpolarised sky ``[T, 0, 0, 0]``
(:func:`mmflow.imaging.polarised.expected_alm`), whose Q, U, V are what the beam model leaves of I
in them. Writes ``stokes.zarr``; the products stage makes the maps.

The transfer coefficients are the reference kernels (six spherical-harmonic transforms per
baseline and correlation, the whole Gram of a channel in memory: ``16 sum_m (4 L_m)^2`` bytes):
arrays of tens of antennas and lmax of a few tens to ~100 (docs/stokes.md); ``mmflow plan``
states the memory.
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import is_full_stokes, padded_alm
from mmflow.imaging.polarised import accumulate_polarised_normal, expected_alm, solve_polarised, \
    stokes_eps
from mmflow.io.run_stores import stokes_store
from mmflow.mmode.noise import relative_weights
from mmflow.mmode.polarised import CORRELATIONS, make_polarised_grid
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit
from mmflow.telescope.beam_factory import make_jones
from mmflow.workflow.kernel_args import m_filters
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.task_key import TaskKey

STOKES_CONFIG = ("mmode.lmax", "beam", "imaging", "transfer.noise_weighting")


def _prepare(ctx):
    mg = ctx.open("mmodes.zarr")
    nf, n_m = mg["mmodes_corr"].shape[:2]
    lmax = ctx.cfg.mmode.lmax
    ctx.create(stokes_store(nf, lmax, n_m - 1))
    return [TaskKey(freq=fi) for fi in range(nf)]


def _task(ctx, key):
    cfg = ctx.cfg
    fi, lmax = key.freq, cfg.mmode.lmax
    vg = ctx.open("vis.zarr")
    freq = float(vg["freqs_hz"][fi])
    pairs = vg["pairs"][:]
    mm = ctx.read("mmodes.zarr", "mmodes_corr", (slice(fi, fi + 1),))[0]  # (m, pm, corr, bl)
    inv_var = ctx.read("mmodes.zarr", "inv_var_corr", (slice(fi, fi + 1),))[0]  # (corr, bl)
    w = relative_weights(inv_var) if cfg.transfer.noise_weighting else (inv_var > 0).astype(float)
    keep = np.flatnonzero(w.max(axis=0) > 0)  # baselines with data in some correlation
    jones = make_jones(cfg.beam.model_dump())
    tel = ctx.telescope()
    b = baselines_in_wavelengths(tel, pairs[keep], freq)
    grid = make_polarised_grid(tel.lat_rad, jones, freq, lmax,
                               fringe_bandlimit(np.linalg.norm(b, axis=1), jones.lmax_hint))
    normal = accumulate_polarised_normal(grid, b, mm[:lmax + 1, :, :, keep][None], w[:, keep], CORRELATIONS)
    eps, filters = stokes_eps(cfg.imaging.eps, cfg.imaging.eps_pol), m_filters(cfg.imaging)
    alm = solve_polarised(normal, eps, filters)[0]  # (4, n_alm)
    unpolarised = np.zeros_like(alm)
    unpolarised[0] = alm[0]
    leak = expected_alm(normal, unpolarised, eps, filters)[0]
    out = ctx.open("stokes.zarr", mode="r+")
    n_m = out["alm"].shape[2]
    ctx.write(out, "alm", (slice(fi, fi + 1),), padded_alm(alm, lmax, n_m)[None])
    ctx.write(out, "leakage", (slice(fi, fi + 1),), padded_alm(leak, lmax, n_m)[None])
    return {"baselines": int(len(keep)), "eps": list(eps)}


STAGE = Stage("stokes", STOKES_CONFIG, ("vis.zarr", "mmodes.zarr"), ("stokes.zarr",), _prepare, _task,
              enabled=lambda cfg: is_full_stokes(cfg.imaging.stokes),
              description="full-Stokes transfer coefficients (E-field beam), normal equations over T, E, B, V and "
              "Tikhonov per Stokes, per frequency; leakage of the unpolarised sky")
