"""Kernel keyword arguments built from configuration sections, one function per kernel.

Kernels take plain values, never a configuration (docs/architecture.md); the stages that call the
same kernel build its arguments here, so they cannot drift apart.
"""
from __future__ import annotations


def m_filters(imaging):
    """Keyword arguments of :func:`mmflow.imaging.filters.filter_mask` from the ``imaging`` section.

    Used by the ``solve`` stage (the unknowns removed before solving) and the ``clean`` stage (the
    same coefficients kept out of the PSFs and the model), so both filter exactly alike.

    Parameters
    ----------
    imaging : ImagingConfig or ConfigView of it
        Reads ``zero_monopole``, ``filter_m0`` and ``filter_m1_lmin``.

    Returns
    -------
    dict
        ``{"zero_monopole": bool, "filter_m0": bool, "filter_m1_lmin": int or None}``.
    """
    return dict(zero_monopole=imaging.zero_monopole, filter_m0=imaging.filter_m0,
                filter_m1_lmin=imaging.filter_m1_lmin)
