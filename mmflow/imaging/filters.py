"""m-filters applied in the frame of date (paper section 4): terrestrial pickup lives there.

Defaults follow the paper: ``a_00 = 0``; all ``m = 0``; ``m = 1`` with ``l > 100``.
Apply the same filter to PSFs so CLEAN removes the rings it creates around the NCP.
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import m_slice


def filter_mask(m, lmax, zero_monopole=True, filter_m0=True, filter_m1_lmin=100):
    """Boolean mask over ``l = m..lmax`` of the coefficients *kept* in block m."""
    ell = np.arange(m, lmax + 1)
    keep = np.ones(len(ell), bool)
    if m == 0 and filter_m0:
        keep[:] = False
    if m == 0 and zero_monopole:
        keep[ell == 0] = False
    if m == 1 and filter_m1_lmin is not None:
        keep[ell > filter_m1_lmin] = False
    return keep


def apply_filters(alm, lmax, **kw):
    """Apply :func:`filter_mask` to a full healpy-layout alm vector (returns a copy)."""
    out = np.array(alm, copy=True)
    for m in (0, 1):
        if m <= lmax:
            sl = m_slice(lmax, m)
            out[sl] = np.where(filter_mask(m, lmax, **kw), out[sl], 0)
    return out
