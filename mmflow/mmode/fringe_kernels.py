"""Compiled inner loop of the transfer-matrix Fourier stage (numba).

:func:`fringe_folds` writes the beam-weighted fringes of a block of north rings and their
mirror rings straight into the two FFT inputs ``A_n f_n +/- A_s f_s`` in one pass over memory,
where numpy needs about ten (matmul, reduce, cast, sin, cos, two beam products, the mirror
rotation, sum and difference); :func:`kernel_fringe_folds` does the same with complex kernels
(every Stokes kernel of every correlation) for the full-Stokes path, from a ring's fringes formed once
(:func:`ring_fringes`); :func:`scatter_m` copies a block's m of the transforms into the Fourier arrays.

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
    def ring_fringes(vn, vs, b_turns, out):
        nphi = vn.shape[1]
        nb = b_turns.shape[0]
        for c in range(nb):  # rows: north cos, sin; mirror cos, sin (each contiguous in phi: the loops vectorize)
            bx, by, bz = b_turns[c, 0], b_turns[c, 1], b_turns[c, 2]
            for h, v in ((0, vn), (2, vs)):
                re, im = out[c, h], out[c, h + 1]
                for j in range(nphi):
                    t = v[0, j] * bx + v[1, j] * by + v[2, j] * bz
                    sn, co = _sincos_turns(real(t - np.rint(t)), sin_c, cos_c, two_pi, quarter)
                    re[j] = co
                    im[j] = sn

    @numba.njit(nogil=True, boundscheck=False, cache=True)
    def kernel_folds(fr, kr_n, ki_n, kr_s, ki_s, out_sum, out_diff):
        nf, nphi = kr_n.shape
        nb = fr.shape[0]
        for f in range(nf):
            anr, ani, asr, asi = kr_n[f], ki_n[f], kr_s[f], ki_s[f]
            for c in range(nb):
                f0, f1, f2, f3 = fr[c, 0], fr[c, 1], fr[c, 2], fr[c, 3]
                s, d = out_sum[f, c], out_diff[f, c]  # interleaved re, im (the complex arrays' real views)
                for j in range(nphi):
                    nr = anr[j] * f0[j] - ani[j] * f1[j]
                    ni = anr[j] * f1[j] + ani[j] * f0[j]
                    sr = asr[j] * f2[j] - asi[j] * f3[j]
                    si = asr[j] * f3[j] + asi[j] * f2[j]
                    s[2 * j] = nr + sr
                    s[2 * j + 1] = ni + si
                    d[2 * j] = nr - sr
                    d[2 * j + 1] = ni - si

    return fringe_folds, ring_fringes, kernel_folds


def ring_fringes(vec_n, vec_s, b_turns, dtype):
    """The fringes of one north ring and its mirror for every baseline, for :func:`kernel_fringe_folds`.

    ``out[c] = (cos, sin)(2 pi b_c.r_n,j), (cos, sin)(2 pi b_c.r_s,j)``: real ``(nb, 4, nphi)`` of ``dtype``
    (float32 or float64), each row contiguous in ``j``.

    Parameters
    ----------
    vec_n, vec_s : (nphi, 3) float64 directions of the two rings; b_turns : (nb, 3) float64 baselines
    """
    kern = _kernels(np.dtype(dtype).name)[1]
    out = np.empty((len(b_turns), 4, len(vec_n)), dtype)
    kern(np.ascontiguousarray(np.asarray(vec_n, float).T), np.ascontiguousarray(np.asarray(vec_s, float).T),
         np.ascontiguousarray(b_turns, float), out)
    return out


def kernel_fringe_folds(fringes, k_n, k_s, out_sum, out_diff):
    """Complex kernels times the fringes of one north ring and its mirror, folded, for the full-Stokes path.

    ``out_sum/out_diff[f, c, j] = K_n[f, j] e^{2 pi i b_c.r_n,j} +/- K_s[f, j] e^{2 pi i b_c.r_s,j}``
    (:mod:`mmflow.mmode.polarised_transfer`: f runs over Stokes kernels of the correlations), phi last so
    that each row's FFT reads contiguous memory (docs/stokes.md).

    Parameters
    ----------
    fringes : (nb, 4, nphi) real, :func:`ring_fringes` (its precision is the output's)
    k_n, k_s : (nf, nphi) complex kernels on the two rings
    out_sum, out_diff : (nf, nb, nphi) complex64 or complex128 (contiguous), written in full
    """
    real = fringes.dtype
    kern = _kernels(np.dtype(real).name)[2]
    parts = [np.ascontiguousarray(p, real) for k in (k_n, k_s) for p in (k.real, k.imag)]
    n = out_sum.shape
    kern(fringes, *parts, out_sum.view(real).reshape(n[0], n[1], 2 * n[2]),
         out_diff.view(real).reshape(n[0], n[1], 2 * n[2]))


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


@numba.njit(nogil=True, boundscheck=False, cache=True)
def _scatter(src, targets, i, fa, fx, fc, signs, m0, m1):
    n_h, nb, n = src.shape
    for h in range(n_h):
        t = targets[h]
        for j in range(len(fa)):
            a, x, c, s = fa[j], fx[j], fc[j], signs[j]
            for k in range(m1 - m0):  # each m's columns contiguous in the Fourier arrays
                m = m0 + k
                neg = (n - m) % n
                out = t[k, a, i, x, c]
                for b in range(nb):
                    out[b] = s * src[h, b, m]
                    out[nb + b] = s * src[h, b, neg]


def scatter_m(src, fsum, fdiff, i, kernels, signs, m_range):
    """Copy the block's m of one kernel's transformed rows into the Fourier arrays of ring ``i``, compiled (no
    Python per copy, no fancy-indexed temporaries, the GIL released).

    ``fsum/fdiff[m - m0, a, i, x, c, b] = sign F[b, m]`` and ``[..., nb + b] = sign F[b, -m]`` (index ``n - m``)
    for each target kernel ``(a, x, c)`` of ``kernels`` (``(3, k)`` int: field pair, field, correlation) with its
    ``sign`` (+1 or -1: negation is exact), ``F`` the rows ``src`` ``(2 [sum, diff], nb, n_phi)``.
    """
    k = np.asarray(kernels, np.int64)
    _scatter(src, (fsum, fdiff), int(i), k[0], k[1], k[2], np.asarray(signs, src.real.dtype), int(m_range[0]),
             int(m_range[1]))
