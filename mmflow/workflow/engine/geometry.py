"""The work geometry a run's settings and stores give: m range, sidereal bins, integrations, split shares.

Stages share these (``mmodes`` and every stage after it use :func:`mmax_of`; ``ingest``'s check and
the configuration checks :func:`n_bins_of`; ``clean`` and the CLEAN products :func:`split_fractions`),
so they live here and no stage module imports another. The time chunks are in
:mod:`mmflow.workflow.engine.chunking`.
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import SIDEREAL_DAY_S, STOKES_LMAX_DEFAULT
from mmflow.mmode.splits import split_shares
from mmflow.io.run_stores import STORES

#: sampled sidereal angles of an interpolated diffuse sky per task of the simulate stage's first phase
DIFFUSE_SAMPLE_BLOCK = 8


def mmax_of(cfg):
    """The largest m imaged: ``mmode.mmax``, else ``mmode.lmax``."""
    return cfg.mmode.mmax if cfg.mmode.mmax is not None else cfg.mmode.lmax


def stokes_lmax_of(cfg):
    """The band limit of Q, U and V in full-Stokes imaging: ``imaging.stokes_lmax``, else
    ``min(mmode.lmax, STOKES_LMAX_DEFAULT)``; never above ``mmode.lmax``."""
    lp = cfg.imaging.stokes_lmax
    return min(cfg.mmode.lmax, STOKES_LMAX_DEFAULT if lp is None else lp)


def n_bins_of(cfg, integration_s):
    """Sidereal bins of the m-mode transform: ``mmode.n_bins``, else
    ``N = round(T_sid / tau)`` for integrations of ``tau`` seconds (one bin per integration)."""
    return cfg.mmode.n_bins or int(round(SIDEREAL_DAY_S / integration_s))


def run_freqs_hz(cfg, ingest=None):
    """The run's channels (Hz), as its telescope holds them and the beam must cover: for ingested data
    those of ``ingest``, the ingest plan (:func:`mmflow.io.ingest.plan_ingest`, or a plan record's copy):
    the channels the ingest selects from the files (every channel, or the one nearest each of
    ``observation.freqs_mhz``, averaged with ``input.average_channels``); a simulation's (``ingest``
    None) ``observation.freqs_mhz``, 40 MHz when null."""
    if ingest is not None:
        return np.asarray(ingest.freqs_hz, float)
    return np.asarray(cfg.observation.simulated_freqs_mhz(), float) * 1e6


def fit_bins(splits, n_bins):
    """The bins of the smallest data split, which bound every baseline's m-mode fit: half of them less
    one for even / odd splits, else ``n_bins - 1`` (band limits up to half of it)."""
    return n_bins // 2 - 1 if {"even", "odd"} & set(splits) else n_bins - 1


def fit_band(tel, freq_hz, n_fit, pairs=None):
    """Each baseline's band limit ``M_b`` in the m-mode fit at ``freq_hz``: its fringe's
    (:meth:`mmflow.telescope.array.Telescope.baseline_lmax`), at most half the ``n_fit`` bins of the smallest
    split (:func:`fit_bins`); the mmodes stage fits with it and its cost model sizes the fit by it."""
    return tel.baseline_lmax(freq_hz, n_fit // 2, pairs)


def interpolates_diffuse(cfg):
    """Whether the simulate stage sums the diffuse sky at a few sidereal angles and interpolates it to
    every integration (:mod:`mmflow.simulate.drift_modes`): every simulation with a diffuse sky (a
    full-Stokes one its four correlations: the unpolarised sky's drift scan through any beam is a
    trigonometric polynomial of degree ``sky.diffuse_lmax`` in the sidereal angle)."""
    return bool(cfg.sky.diffuse)


def n_integrations(cfg):
    """Integrations of a simulated scan: ``observation.n_integrations``, else one sidereal day's
    ``round(T_sid / tau)``."""
    o = cfg.observation
    return o.n_integrations or int(round(SIDEREAL_DAY_S / o.integration_s))


def split_fractions(ctx, fi):
    """``{split: f_k}`` at frequency ``fi``: each split's share of the unflagged samples, summed over
    baselines (``mmodes.zarr``'s ``n_samples``, :func:`mmflow.mmode.splits.split_shares`): the ``f_k``
    of the per-day jackknife and of the day/night map, for any stage that reads ``mmodes.zarr``."""
    g = ctx.open(STORES.mmodes)
    counts = ctx.read(STORES.mmodes.n_samples, (slice(None), slice(fi, fi + 1)))[:, 0].sum(axis=-1)
    return split_shares(counts, list(g.attrs["splits"]))
