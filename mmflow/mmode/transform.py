"""Sidereal regridding and the m-mode transform.

``V_m = (1/N) sum_n V(phi_n) exp(-i m phi_n)``, ``phi_n = 2 pi n / N`` (see conventions).
Stored as ``mmodes[m, 0, b] = V_m`` and ``mmodes[m, 1, b] = conj(V_{-m})`` (slot unused at m=0).
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import TWO_PI
from mmflow.errors import CoverageError, InputError


def sidereal_bins(lsts, vis, weights=None, n_bins=None, min_coverage=1.0, source="visibilities"):
    """Average time-ordered data onto ``n_bins`` equal sidereal bins centred on ``2 pi n / N``.

    Several days fold onto the same bins (weighted mean). Samples with zero weight or
    non-finite values are ignored: zero is a value, never a flag.

    Parameters
    ----------
    lsts : ndarray (n_time,)
        Sidereal angle of each sample in radians (any start, any number of days).
    vis : ndarray (n_time, ...)
    weights : ndarray broadcastable to ``vis``, optional
        Non-negative weights (e.g. 1/sigma^2 or 1 for good, 0 for flagged).
    n_bins : int
        Number of sidereal bins; must be ``>= 2 mmax + 1`` for the transform.
    min_coverage : float
        Fraction of bins (per baseline, median over baselines) that must hold data.

    Returns
    -------
    binned : ndarray (n_bins, ...) complex
    bin_weight : ndarray (n_bins, ...) float, the summed weights
    offset : ndarray (n_bins,) float
        Weighted mean of ``phi - 2 pi n / N`` of the samples in each bin (radians). Pass it
        to :func:`mmode_transform` so that samples keep their exact LSTs: a drift scan whose
        LSTs are not on the bin grid is otherwise shifted by up to half a bin in RA.

    Raises
    ------
    CoverageError
        When less than ``min_coverage`` of the sidereal day holds data.
    InputError
        For NaN/inf in visibilities that are not flagged (weight > 0).
    """
    lsts = np.asarray(lsts, float)
    vis = np.asarray(vis)
    if len(lsts) != len(vis):
        raise InputError(source, "lst", f"{len(lsts)} LSTs for {len(vis)} integrations",
                         "give one LST per integration")
    w = np.ones(vis.shape) if weights is None else np.broadcast_to(np.asarray(weights, float), vis.shape)
    if np.any(w < 0):
        raise InputError(source, "weights", "negative weights", "weights must be >= 0 (0 = flagged)")
    bad = ~np.isfinite(vis) & (w > 0)
    if np.any(bad):
        t_bad = np.unique(np.nonzero(bad)[0])[:5]
        raise InputError(source, "visibilities", f"{int(bad.sum())} NaN/inf values that are not flagged "
                         f"(first integrations {t_bad.tolist()})", "flag them (weight 0) or fix the data")
    idx, delta = bin_index(lsts, n_bins)
    flat_v = np.where(w > 0, vis, 0).reshape(len(vis), -1)
    flat_w = w.reshape(len(vis), -1)
    acc = np.zeros((n_bins, flat_v.shape[1]), np.complex128)
    wsum = np.zeros((n_bins, flat_v.shape[1]))
    np.add.at(acc, idx, flat_v * flat_w)
    np.add.at(wsum, idx, flat_w)
    coverage = float(np.median(np.mean(wsum > 0, axis=0)))
    if coverage < min_coverage:
        raise CoverageError(source, "lst", f"only {coverage:.1%} of {n_bins} sidereal bins hold data "
                            f"(need {min_coverage:.0%})",
                            "observe a full sidereal day, lower mmode.min_coverage, or use fewer bins")
    with np.errstate(invalid="ignore", divide="ignore"):
        binned = np.where(wsum > 0, acc / np.where(wsum > 0, wsum, 1), 0)
    shape = (n_bins,) + vis.shape[1:]
    w_t = flat_w.sum(axis=1)
    off_acc = np.zeros(n_bins)
    off_w = np.zeros(n_bins)
    np.add.at(off_acc, idx, w_t * delta)
    np.add.at(off_w, idx, w_t)
    offset = np.where(off_w > 0, off_acc / np.where(off_w > 0, off_w, 1), 0.0)
    return binned.reshape(shape), wsum.reshape(shape), offset


def bin_index(lsts, n_bins):
    """Nearest sidereal bin ``n = round(N phi / 2 pi) mod N`` of each LST and its offset
    ``phi - 2 pi n / N`` (radians, within half a bin): the binning of :func:`sidereal_bins`."""
    pos = np.mod(np.asarray(lsts, float), TWO_PI) / TWO_PI * n_bins
    return np.round(pos).astype(int) % n_bins, (pos - np.round(pos)) * TWO_PI / n_bins


def bin_occupancy(lsts, good, n_bins):
    """Which sidereal bins (:func:`bin_index`, the binning of :func:`sidereal_bins`) hold an unflagged
    sample: ``(n_bins,) + good.shape[1:]`` booleans from ``good`` ``(n_time, ...)`` (True: weight > 0),
    the ``bin_weight > 0`` of :func:`sidereal_bins` without summing values (one sort of the times)."""
    good = np.asarray(good, bool)
    out = np.zeros((n_bins,) + good.shape[1:], bool)
    if not len(good):
        return out
    idx, _ = bin_index(lsts, n_bins)
    order = np.argsort(idx, kind="stable")
    bins, starts = np.unique(idx[order], return_index=True)
    out[bins] = np.logical_or.reduceat(good[order], starts, axis=0)
    return out


def bin_coverage(lsts, n_bins):
    """Fraction of the ``n_bins`` sidereal bins (:func:`bin_index`) that hold at least one of the finite
    ``lsts``: the most of the sidereal day any baseline of those integrations can cover, flags aside."""
    lsts = np.asarray(lsts, float)
    lsts = lsts[np.isfinite(lsts)]
    return len(np.unique(bin_index(lsts, n_bins)[0])) / n_bins if lsts.size else 0.0


def mmode_transform(binned, mmax, offset=None):
    """m-modes of sidereally binned data, shape ``(mmax + 1, 2) + binned.shape[1:]``.

    ``out[m, 0] = V_m``, ``out[m, 1] = conj(V_{-m})`` with ``V_m = (1/N) sum_n V_n e^{-i m phi_n}``,
    ``phi_n = 2 pi n / N + offset_n``: an FFT when the offsets vanish, else a direct DFT (one GEMM).
    """
    n = binned.shape[0]
    if n < 2 * mmax + 1:
        raise InputError("m-mode transform", "n_bins", f"{n} sidereal bins cannot resolve mmax={mmax}",
                         f"use at least {2 * mmax + 1} bins (or lower mmax)")
    out = np.empty((mmax + 1, 2) + binned.shape[1:], np.complex128)
    if offset is None or not np.any(offset):
        spec = np.fft.fft(binned, axis=0) / n  # sum V e^{-2 pi i k n / N} / N
        out[:, 0] = spec[:mmax + 1]
        out[:, 1] = np.conj(spec[(-np.arange(mmax + 1)) % n])
    else:
        phi = TWO_PI * np.arange(n) / n + np.asarray(offset, float)
        ms = np.arange(-mmax, mmax + 1)
        dft = np.exp(-1j * np.outer(ms, phi)) / n  # (2 mmax + 1, n)
        spec = (dft @ binned.reshape(n, -1)).reshape((2 * mmax + 1,) + binned.shape[1:])
        out[:, 0] = spec[mmax:]
        out[:, 1] = np.conj(spec[mmax::-1])
    out[0, 1] = 0
    return out


def mmode_noise_variance(bin_weight, sigma2_per_unit_weight=1.0):
    """Variance of each m-mode from bin weights (inverse-variance weights -> 1/sum w per bin).

    ``Var(V_m) = (1/N^2) sum_n Var(V_n)``; identical for every m (white in sidereal time).
    """
    n = bin_weight.shape[0]
    with np.errstate(divide="ignore"):
        var_n = np.where(bin_weight > 0, sigma2_per_unit_weight / np.where(bin_weight > 0, bin_weight, 1), 0)
    return var_n.sum(axis=0) / n**2


def block_vector(mmodes, m):
    """The data vector of one m block: ``V_m`` rows, then ``conj(V_{-m})`` rows for m > 0."""
    return mmodes[m, 0] if m == 0 else np.concatenate([mmodes[m, 0], mmodes[m, 1]])


SPLITS = ("full", "even", "odd")


def split_mmode_transform(binned, mmax, offset, splits=("full",)):
    """m-modes of several splits of the sidereal bins, shape ``(n_split, mmax + 1, 2, ...)``.

    ``full`` uses every bin; ``even`` / ``odd`` use bins ``2k`` / ``2k + 1`` only (jackknife
    halves), each as a transform over ``N/2`` bins at its own phases
    ``phi = 2 pi (2k) / N`` and ``2 pi (2k + 1) / N``: the odd half carries the
    m-dependent phase of its one-bin offset, ``exp(-i m 2 pi / N)``. Every split estimates the
    same ``V_m`` (for ``mmax < N/4``) with its own noise, so one transfer pass projects them all.
    """
    return np.stack([mmode_transform(binned[rows], mmax, phase)
                     for rows, phase in split_bins(binned.shape[0], offset, splits)])


def split_bins(n_bins, offset, splits):
    """The sidereal bins of each split and their phase offsets: ``(rows, offset)`` per split.

    ``full``: every bin, ``offset`` (zeros when None); ``even`` / ``odd``: bins ``2k + s``
    (``s = 0, 1``) at phase offsets ``offset[2k + s] + s 2 pi / N`` relative to the grid
    ``2 pi k / (N / 2)`` of the half. Time subsets (``day<k>``, ``day``, ``night``) are binned on
    their own (:mod:`mmflow.mmode.splits`).
    """
    offset = np.zeros(n_bins) if offset is None else np.asarray(offset, float)
    out = []
    for s in splits:
        if s == "full":
            out.append((slice(None), offset))
        elif s in ("even", "odd"):
            start = 0 if s == "even" else 1
            if n_bins % 2:
                raise InputError("m-mode transform", "mmode.splits", f"even/odd splits need an even number of "
                                 f"sidereal bins, not {n_bins}", "set mmode.n_bins to an even number")
            out.append((slice(start, None, 2), offset[start::2] + start * TWO_PI / n_bins))
        else:
            raise InputError("m-mode transform", "mmode.splits", f"unknown split '{s}'",
                             f"use {SPLITS} (time subsets day<k> / day / night are binned on their own: "
                             "mmflow.mmode.splits)")
    return out
