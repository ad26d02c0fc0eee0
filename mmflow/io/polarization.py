"""The polarisations mmflow keeps from a file, chosen by pyuvdata polarisation NUMBER, and
Stokes I formed from them.

pyuvdata (AIPS memo 117) numbers: Stokes / pseudo-Stokes I = 1 (``I``, ``pI``), RR = -1,
LL = -2, XX = -5, YY = -6; the cross hands are RL = -3, LR = -4, XY = -7, YX = -8. The
string labels depend on the feeds (pyuvdata calls XX/YY ``ee``/``nn`` when the telescope's
``x_orientation`` is east, and ``hh``/``vv`` for some instruments), so mmflow never looks at
them: it works from the numbers.

Stokes I (docs/conventions.md) is, in order of preference:

* the file's I / pI (number 1) as it is;
* ``(XX + YY) / 2`` (linear feeds, the paper's section 2; also from 4-pol files);
* ``(RR + LL) / 2`` (circular feeds);
* a single parallel hand (XX, YY, RR or LL alone) as it is, with a warning: for an
  unpolarised sky XX = YY = I.

Cross hands alone (XY, YX, RL, LR: no parallel hand) and Stokes Q/U/V alone carry no Stokes
I and are refused.

Ingest keeps the polarisations that make Stokes I *separately* (``vis.zarr``'s ``pol`` axis,
named by :func:`stored_names`: ``xx, yy``, ``rr, ll``, ``I`` or one parallel hand): gains
are per antenna *and* polarisation, so calibration and peeling act on each hand before
:func:`stokes_i` combines them where the data are next read. A Stokes-I sample is flagged
when any polarisation it uses is flagged; its sample count is the smallest of theirs.

The cross hands of a parallel pair (XY and YX beside XX and YY; RL and LR beside RR and LL;
:func:`cross_recipe`) are carried too, on their own polarisation axis (``vis.zarr``'s
``vis_cross`` / ``weights_cross``, named by ``attrs["cross_pols"]``), so that the arrays every
stage reads (``vis``, ``weights``: the hands calibration solves and Stokes I averages) are the
same whether a file holds two polarisations or four.
"""
from __future__ import annotations

import numpy as np

from mmflow.errors import InputError

STOKES_I = 1
PAIRS = ((-5, -6), (-1, -2))  # (XX, YY), (RR, LL)
PARALLEL = (-5, -6, -1, -2)
_NAMES = {1: "I", 2: "Q", 3: "U", 4: "V", -1: "RR", -2: "LL", -3: "RL", -4: "LR", -5: "XX", -6: "YY",
          -7: "XY", -8: "YX"}


def pol_names(numbers):
    """Feed-independent names of pyuvdata polarisation numbers (``-5 -> 'XX'``)."""
    return [_NAMES.get(int(p), str(int(p))) for p in np.ravel(numbers)]


def stokes_i_recipe(pol_numbers, what="input"):
    """Which polarisation indices make Stokes I, and with what weight.

    Parameters
    ----------
    pol_numbers : array_like of int
        The file's ``polarization_array`` (pyuvdata numbers).
    what : str
        The file, for the error message.

    Returns
    -------
    indices : tuple of int
        Positions along the file's polarisation axis that are combined.
    single : bool
        True when one parallel hand alone stands in for Stokes I.

    Stokes I = sum(data[..., indices]) / len(indices).
    """
    pols = [int(p) for p in np.ravel(pol_numbers)]
    if STOKES_I in pols:
        return (pols.index(STOKES_I),), False
    for a, b in PAIRS:
        if a in pols and b in pols:
            return (pols.index(a), pols.index(b)), False
    par = [p for p in pols if p in PARALLEL]
    if len(par) == 1:
        return (pols.index(par[0]),), True
    raise InputError(what, "polarization_array",
                     f"cannot form Stokes I from polarisations {pol_names(pols)} (numbers {pols}): "
                     "no Stokes I and no parallel-hand pair (cross hands alone carry no Stokes I)",
                     "provide XX and YY (pyuvdata also calls them ee/nn), RR and LL, or pseudo-Stokes pI")


_STORED = {1: "I", -1: "rr", -2: "ll", -5: "xx", -6: "yy", -3: "rl", -4: "lr", -7: "xy", -8: "yx"}
CROSS = {(-5, -6): (-7, -8), (-1, -2): (-3, -4)}  # (XX, YY): (XY, YX); (RR, LL): (RL, LR)




def cross_recipe(pol_numbers, indices):
    """Positions of the cross hands that go with the parallel pair at ``indices`` (``()`` when the
    Stokes-I recipe is not a parallel pair, or the file holds no cross hand), in the order XY, YX
    (RL, LR)."""
    pols = [int(p) for p in np.ravel(pol_numbers)]
    pair = tuple(pols[i] for i in indices)
    return tuple(pols.index(c) for c in CROSS.get(pair, ()) if c in pols)


def stored_names(pol_numbers, indices):
    """Names of the kept polarisations along ``vis.zarr``'s ``pol`` axis (``['xx', 'yy']``)."""
    pols = [int(p) for p in np.ravel(pol_numbers)]
    return [_STORED[pols[i]] for i in indices]


def select_pols(data, flags, nsample, indices):
    """The kept polarisations ``(..., len(indices))`` of ``(..., npol)`` arrays, in recipe order."""
    idx = list(indices)
    return data[..., idx], flags[..., idx], nsample[..., idx]


def stokes_i(vis, weights):
    """Stokes I and its weights from ``(..., npol)`` arrays of the kept polarisations.

    ``I = mean_p V_p`` (``(XX + YY) / 2``; one kept polarisation is returned as it is); the
    weight is the smallest of the polarisations' (0 where any hand is flagged).
    """
    if vis.shape[-1] == 1:
        return vis[..., 0], weights[..., 0]
    return vis.mean(axis=-1), weights.min(axis=-1)


def stokes_i_variance(variances):
    """``Var(I) = sum_p Var(V_p) / n_pol^2`` for independent noise in the kept polarisations
    (``(..., npol)``): two hands halve the single-hand variance."""
    n = variances.shape[-1]
    return variances.sum(axis=-1) / n**2


#: pyuvdata's ``pol_convention`` values: how the parallel hands relate to Stokes I
POL_CONVENTIONS = {"sum": "I = XX + YY (an unpolarised source of flux S gives XX = YY = S/2: matvis, "
                          "pyuvsim, hera_sim, FHD)",
                   "avg": "I = (XX + YY) / 2 (XX = YY = S: CASA, AIPS, mmflow's own simulator)"}


def pol_factor(file_convention, requested, calibrated_here, what):
    """The factor that takes a file's parallel (and cross) hands to mmflow's convention, and the
    convention it assumed: ``(factor, convention)``.

    mmflow stores and models visibilities in the ``avg`` convention, XX = YY = S for an unpolarised
    source of flux S (``I = (XX + YY) / 2``, docs/conventions.md). Data in the ``sum`` convention
    (XX = S/2) are doubled on ingest. ``requested`` is ``input.pol_convention``: ``sum`` / ``avg``
    as the user says, or ``auto``: the file's own ``pol_convention`` (pyuvdata writes it in UVH5,
    uvfits, MS and Miriad files). When neither says, a calibrated run (``calibrated_here``) needs none
    (the gains, solved against a sky model in mmflow's convention, absorb any factor: ``avg`` is
    assumed and stated), and an uncalibrated one is refused: halving the flux silently is never an
    option.
    """
    convention = file_convention if requested == "auto" else requested
    if convention is None:
        if calibrated_here:
            return 1.0, "avg"
        raise InputError(what, "pol_convention", "the file does not say how its XX / YY relate to Stokes I "
                         "(pyuvdata's pol_convention is unset) and no calibration sets the flux scale",
                         "set input.pol_convention=sum for pyuvdata-family simulations (matvis, pyuvsim, "
                         "hera_sim: XX = I/2) or input.pol_convention=avg for CASA-style data (XX = I), or "
                         "calibrate.enabled=true")
    if convention not in POL_CONVENTIONS:
        raise InputError(what, "pol_convention", f"unknown polarisation convention {convention!r}",
                         "set input.pol_convention to sum or avg")
    return (2.0 if convention == "sum" else 1.0), convention
