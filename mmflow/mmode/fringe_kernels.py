"""Compiled inner loop of the transfer-matrix Fourier stage (numba).

:func:`fringe_folds` writes the beam-weighted fringes of a block of north rings and their
mirror rings straight into the two FFT inputs ``A_n f_n +/- A_s f_s`` in one pass over memory,
where numpy needs about ten (matmul, reduce, cast, sin, cos, two beam products, the mirror
rotation, sum and difference); :func:`kernel_fringe_folds` does the same with complex kernels
(every Stokes kernel of every correlation) for the full-Stokes path.

The fringe phase ``t = b . r`` (turns) is formed and reduced to ``[-1/2, 1/2]`` in float64,
then ``sin/cos(2 pi t)`` come from a quarter-turn reduction and Taylor polynomials in the
working precision (truncation < 2e-9 in float32, < 1e-16 in float64) so that the loop
vectorizes. Kernels are compiled per precision on first use and release the GIL.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numba
import numpy as np
from mmflow.conventions import complex_dtype


def _taylor(odd, n_terms):
    """Taylor coefficients of sin (odd) or cos (even) in powers of y**2."""
    start = 1 if odd else 0
    return [(-1) ** k / math.factorial(2 * k + start) for k in range(n_terms)]


@numba.njit(inline="always", cache=True)
def _sincos_turns(t, s, c, two_pi, quarter):
    """``(sin 2 pi t, cos 2 pi t)`` for ``|t| <= 1/2`` from the Taylor coefficients ``s``, ``c`` (9 each,
    in the working precision, as are ``t``, ``two_pi`` and ``quarter``)."""
    q = np.rint(t * 4)
    y = (t - q * quarter) * two_pi  # |y| <= pi/4
    y2 = y * y
    sn = y * (
        s[0]
        + y2 * (s[1] + y2 * (s[2] + y2 * (s[3] + y2 * (s[4] + y2 * (s[5] + y2 * (s[6] + y2 * (s[7] + y2 * s[8])))))))
    )
    cs = c[0] + y2 * (c[1] + y2 * (c[2] + y2 * (c[3] + y2 * (c[4] + y2 * (c[5] + y2 * (c[6] + y2 * (c[7]
                                                                                                 + y2 * c[8])))))))
    qi = int(q) & 3  # rotate by q quarter turns
    odd = (qi & 1) == 1
    ss = cs if odd else sn
    cc = sn if odd else cs
    ss = -ss if (qi & 2) == 2 else ss
    cc = -cc if ((qi + 1) & 2) == 2 else cc
    return ss, cc


@lru_cache(maxsize=None)
def _kernels(real_name):
    """Compile :func:`fringe_folds` and :func:`kernel_fringe_folds` for float32 or float64 working precision
    (or load them from numba's cache: the closures hold only numbers and numpy types, so their cache keys
    are the same in every process)."""
    real = np.dtype(real_name).type
    cplx = complex_dtype(real).type
    n_terms = 6 if real is np.float32 else 9  # |y| <= pi/4: y^13/13! ~ 2e-11, y^19/19! ~ 1e-19
    sin_c = tuple(real(c) for c in (_taylor(True, n_terms) + [0.0] * 9)[:9])
    cos_c = tuple(real(c) for c in (_taylor(False, n_terms) + [0.0] * 9)[:9])
    two_pi, quarter = real(2 * np.pi), real(0.25)

    @numba.njit(nogil=True, boundscheck=False, cache=True)
    def fringe_folds(vec, b_turns, beam_n, beam_s, rot_re, rot_im, out_sum, out_diff):
        nr, nphi = beam_n.shape
        nb = b_turns.shape[0]
        bx, by, bz = b_turns[:, 0].copy(), b_turns[:, 1].copy(), b_turns[:, 2].copy()
        for r in range(nr):
            for j in range(nphi):
                an = real(beam_n[r, j])
                a_s = real(beam_s[r, j])
                if an == 0 and a_s == 0:
                    out_sum[r, j, :] = 0
                    out_diff[r, j, :] = 0
                    continue
                vx, vy, vz = vec[r, j, 0], vec[r, j, 1], vec[r, j, 2]
                for c in range(nb):
                    t = vx * bx[c] + vy * by[c] + vz * bz[c]
                    s, co = _sincos_turns(real(t - np.rint(t)), sin_c, cos_c, two_pi, quarter)
                    rr, ri = rot_re[r, c], rot_im[r, c]
                    sr = co * rr - s * ri  # the mirror ring's fringe: north times exp(-4 pi i b_z z)
                    si = co * ri + s * rr
                    # an explicit complex type of the working precision keeps the loop vectorized
                    out_sum[r, j, c] = cplx(complex(an * co + a_s * sr, an * s + a_s * si))
                    out_diff[r, j, c] = cplx(complex(an * co - a_s * sr, an * s - a_s * si))

    @numba.njit(nogil=True, boundscheck=False, cache=True)
    def kernel_folds(vec_n, vec_s, b_turns, kr_n, ki_n, kr_s, ki_s, out_sum, out_diff):
        nphi, nf = kr_n.shape
        nb = b_turns.shape[0]
        fr = np.empty((4, nb), real)  # north re, im; south re, im
        for j in range(nphi):
            for c in range(nb):
                for h, v in ((0, vec_n), (2, vec_s)):
                    t = v[j, 0] * b_turns[c, 0] + v[j, 1] * b_turns[c, 1] + v[j, 2] * b_turns[c, 2]
                    sn, co = _sincos_turns(real(t - np.rint(t)), sin_c, cos_c, two_pi, quarter)
                    fr[h, c] = co
                    fr[h + 1, c] = sn
            for f in range(nf):
                anr, ani, asr, asi = kr_n[j, f], ki_n[j, f], kr_s[j, f], ki_s[j, f]
                for c in range(nb):
                    nr = anr * fr[0, c] - ani * fr[1, c]
                    ni = anr * fr[1, c] + ani * fr[0, c]
                    sr = asr * fr[2, c] - asi * fr[3, c]
                    si = asr * fr[3, c] + asi * fr[2, c]
                    out_sum[j, f, c] = cplx(complex(nr + sr, ni + si))
                    out_diff[j, f, c] = cplx(complex(nr - sr, ni - si))

    return fringe_folds, kernel_folds


def kernel_fringe_folds(vec_n, vec_s, b_turns, k_n, k_s, out_sum, out_diff):
    """Complex kernels times the fringes of one north ring and its mirror, folded, for the full-Stokes path.

    ``out_sum/out_diff[j, f, c] = K_n[j, f] e^{2 pi i b_c.r_n,j} +/- K_s[j, f] e^{2 pi i b_c.r_s,j}``
    (:mod:`mmflow.mmode.polarised_transfer`: f runs over the Stokes kernels of every correlation).

    Parameters
    ----------
    vec_n, vec_s : (nphi, 3) float64 directions of the two rings; b_turns : (nb, 3) float64 baselines
    k_n, k_s : (nphi, nf) complex kernels on the two rings
    out_sum, out_diff : (nphi, nf, nb) complex64 or complex128, written in full
    """
    real = out_sum.real.dtype
    kern = _kernels(np.dtype(real).name)[1]
    parts = [np.ascontiguousarray(p, real) for k in (k_n, k_s) for p in (k.real, k.imag)]
    kern(np.ascontiguousarray(vec_n, float), np.ascontiguousarray(vec_s, float), np.ascontiguousarray(b_turns, float),
         *parts, out_sum, out_diff)


def fringe_folds(vec, b_turns, beam_n, beam_s, south_rot, out_sum, out_diff):
    """Beam-weighted fringes of a ring block folded north/south, for the parity-split GEMMs.

    ``out_sum/out_diff[r, j, c] = A(r_n) e^{2 pi i b_c.r_n} +/- A(r_s) e^{2 pi i b_c.r_s}``
    with ``r_n = vec[r, j]`` on north ring r and ``r_s`` its mirror ``(x, y, -z)``, for which
    ``b.r_s = b.r_n - 2 b_z z`` (``south_rot[r, c] = exp(-4 pi i b_z z_r)``).

    Parameters
    ----------
    vec : (nr, nphi, 3) float64 directions; b_turns : (nb, 3) float64 baselines in wavelengths
    beam_n, beam_s : (nr, nphi) power beam on the north and mirror rings
    south_rot : (nr, nb) complex, in the output precision
    out_sum, out_diff : (nr, nphi, nb) complex64 or complex128, written in full
    """
    kern = _kernels(np.dtype(out_sum.real.dtype).name)[0]
    real = out_sum.real.dtype
    kern(vec, b_turns, beam_n, beam_s, np.ascontiguousarray(south_rot.real, real),
         np.ascontiguousarray(south_rot.imag, real), out_sum, out_diff)


def sincos_turns(t, dtype=np.float64):
    """``(sin 2 pi t, cos 2 pi t)`` from the compiled polynomial, for testing."""
    inner = _kernels(np.dtype(dtype).name)[0]
    # reuse fringe_folds on a 1-ring, 1-point grid: direction (1, 0, 0), baselines (t, 0, 0)
    t = np.asarray(t, np.float64).ravel()
    out_s = np.empty((1, 1, len(t)), complex_dtype(dtype).type)
    out_d = np.empty_like(out_s)
    b = np.zeros((len(t), 3))
    b[:, 0] = t
    inner(np.array([[[1.0, 0.0, 0.0]]]), b, np.ones((1, 1)), np.zeros((1, 1)),
          np.ones((1, len(t)), dtype), np.zeros((1, len(t)), dtype), out_s, out_d)
    return out_s[0, 0].imag, out_s[0, 0].real
