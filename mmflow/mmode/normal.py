"""Streaming normal equations: ``G_m = B_m^H N^-1 B_m`` and ``r_m = B_m^H N^-1 v_m``.

Accumulated over baseline chunks with BLAS ``?herk`` (upper triangle) and never storing B.
``N`` is diagonal: one variance per row (from the radiometer equation or from the data).
"""
from __future__ import annotations

import ctypes
import time
from functools import lru_cache

import numpy as np
from scipy.linalg import blas, cython_blas


def herk_upper(a, c=None, alpha=1.0):
    """``C += alpha A^H A`` (upper triangle valid) with ``cherk``/``zherk``; returns C."""
    a = np.asarray(a)
    f = blas.cherk if a.dtype == np.complex64 else blas.zherk
    # BLAS is column-major: A (rows x cols) C-ordered is A^T in Fortran order, so
    # "trans=0" on it computes A^T conj(A^T)^H = conj(A^H A); we conjugate the input instead.
    at = np.conj(a).T  # Fortran-contiguous view of conj(A)^T... ensure layout
    at = np.asfortranarray(at)
    if c is None:
        return f(alpha, at, trans=0, lower=0)
    return f(alpha, at, beta=1.0, c=c, trans=0, lower=0, overwrite_c=1)


@lru_cache(maxsize=None)
def _herk_fn(prefix):
    """BLAS ``cherk``/``zherk`` from scipy's ``cython_blas`` as a ctypes function (releases the GIL).

    Called directly so that a leading sub-block ``C[:n, :n]`` of a Fortran-ordered Gram is
    updated in place through ``ldc`` (scipy's Python wrapper would copy a non-contiguous C).
    """
    api = ctypes.pythonapi
    api.PyCapsule_GetName.restype, api.PyCapsule_GetName.argtypes = ctypes.c_char_p, [ctypes.py_object]
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    cap = cython_blas.__pyx_capi__[prefix + "herk"]
    ptr = api.PyCapsule_GetPointer(cap, api.PyCapsule_GetName(cap))
    real = ctypes.c_float if prefix == "c" else ctypes.c_double
    pint, preal = ctypes.POINTER(ctypes.c_int), ctypes.POINTER(real)
    proto = ctypes.CFUNCTYPE(None, ctypes.c_char_p, ctypes.c_char_p, pint, pint, preal, ctypes.c_void_p, pint,
                             preal, ctypes.c_void_p, pint)
    return proto(ptr), real


def herk_into(gram, a, k, n, lda, alpha=1.0):
    """``G[:n, :n] += alpha A^H A`` (upper triangle) in place, ``A`` the ``k x n`` column-major matrix at ``a``.

    Parameters
    ----------
    gram : (N, N) Fortran-ordered complex64/complex128, ``N >= n``; only its upper triangle is written.
    a : C-ordered array of the same dtype whose memory holds ``A`` column-major with leading
        dimension ``lda >= k``: a C-ordered ``(L, lda)`` array ``X`` is ``A = X[:n, :k]^T``, i.e.
        row ``c`` of ``A`` is column ``c`` of ``X`` (a transfer block ``(l, baseline)``).
    k, n : rows and columns of ``A`` (rank of the update and size of the updated sub-block).
    """
    if n == 0 or k == 0:
        return gram
    if not gram.flags.f_contiguous or a.dtype != gram.dtype or not a.flags.c_contiguous:
        raise ValueError("herk_into: Fortran-ordered Gram and a C-ordered block of its dtype expected")
    if a.shape[-1] != lda or a.size < lda * (n - 1) + k:
        raise ValueError("herk_into: block smaller than its k x n matrix")
    fn, real = _herk_fn("c" if gram.dtype == np.complex64 else "z")
    c_int = ctypes.c_int
    fn(b"U", b"C", ctypes.byref(c_int(n)), ctypes.byref(c_int(k)), ctypes.byref(real(alpha)), a.ctypes.data,
       ctypes.byref(c_int(lda)), ctypes.byref(real(1.0)), gram.ctypes.data, ctypes.byref(c_int(gram.shape[0])))
    return gram


def hermitian_full(c_upper):
    """Fill the lower triangle of an upper-triangle Hermitian matrix, in (at least) complex128:
    ``G[j, i] = conj(G[i, j])`` for ``i < j``, the upper triangle and diagonal as given (the lower
    triangle given is ignored).

    Grams are accumulated and stored in the transfer precision (complex64 for float32), but
    every solve, factorisation and eigenvalue count works in complex128: a float32 Gram's
    Cholesky would lose digits to ``G``'s condition number. One ``n x n`` array is made (a copy
    in complex128), filled in place (:func:`mirror_upper`).
    """
    c = np.asarray(c_upper)
    return mirror_upper(np.array(c, np.promote_types(c.dtype, np.complex128)))


def mirror_upper(g):
    """``g[..., j, i] = conj(g[..., i, j])`` for ``i < j``, in place, a row at a time (no index or temporary
    array of the matrix's size); returns ``g``."""
    n = g.shape[-1]
    for i in range(n - 1):
        g[..., i + 1:, i] = g[..., i, i + 1:].conj()
    return g


def _leading_rows(p, n0, n):
    """``(i, row)`` for each row ``i < n`` of the leading ``n x n`` block of :func:`pack_upper`'s packed
    ``n0 x n0`` triangle ``p``: ``row = G[i, i:n]``, a view of ``p`` (row ``i`` starts at
    ``i n0 - i (i - 1) / 2``)."""
    if p.shape != (packed_size(n0),) or not 0 <= n <= n0:
        raise ValueError(f"{p.shape} is not the packed upper triangle of an {n0} x {n0} matrix (length "
                         f"{packed_size(n0)}) with a leading block of {n}: written by an mmflow that stored the "
                         "squares? Start that run afresh (--force)")
    start = 0
    for i in range(n):
        yield i, p[start:start + n - i]
        start += n0 - i


def upper_block(p, n0, n):
    """The leading ``n x n`` block of the upper triangle :func:`pack_upper` packed into ``p`` (``n0 x n0``),
    zero below the diagonal, in ``p``'s dtype: ``unpack_upper(p, n0)[:n, :n]`` in the one ``n x n`` array it
    returns (a stored Cholesky factor's kept corner)."""
    p = np.asarray(p)
    out = np.zeros((n, n), p.dtype)
    for i, row in _leading_rows(p, n0, n):
        out[i, i:] = row
    return out


def hermitian_block(p, n0, n):
    """The leading ``n x n`` block of the Hermitian matrix whose ``n0 x n0`` upper triangle :func:`pack_upper`
    packed into ``p``, full and in (at least) complex128: ``hermitian_full(unpack_upper(p, n0)[:n, :n])``
    without the ``n0 x n0`` intermediates (a solve task holds this per m on each of its threads: the
    stages' cost models count one such array, ``mmflow.workflow.stages.solve.cost``)."""
    p = np.asarray(p)
    g = np.zeros((n, n), np.promote_types(p.dtype, np.complex128))
    for i, row in _leading_rows(p, n0, n):
        g[i, i:] = row
    return mirror_upper(g)


def pack_leading_upper(a, n0, out):
    """Pack the upper triangle of the ``n x n`` ``a`` as the leading block of an ``n0 x n0`` matrix that is zero
    elsewhere into ``out`` (:func:`pack_upper`'s layout, length ``n0 (n0 + 1) / 2``): ``pack_upper`` of
    ``a`` padded with zeros to ``n0 x n0``, without the padded square. Returns ``out``."""
    a = np.asarray(a)
    n = a.shape[0]
    out[...] = 0
    for i, row in _leading_rows(out, n0, n):
        row[...] = a[i, i:]
    return out


def packed_size(n):
    """Elements of an ``n x n`` matrix's upper triangle, ``n (n + 1) / 2``: the length of :func:`pack_upper`."""
    return n * (n + 1) // 2


def pack_upper(a):
    """The upper triangles of ``a`` (``(..., n, n)``), packed row by row: ``p[..., k] = a[..., i_k, j_k]`` over
    ``(i_k, j_k) = numpy.triu_indices(n)`` (``i_k <= j_k``), ``(..., n (n + 1) / 2)``.

    The stores hold a Hermitian Gram or an upper Cholesky factor so: everything their readers use (the upper
    triangle: :func:`hermitian_full`, LAPACK's ``potrs`` with ``uplo = U``) in about half the bytes.
    """
    a = np.asarray(a)
    i, j = np.triu_indices(a.shape[-1])
    return a[..., i, j]


def unpack_upper(p, n):
    """The ``(..., n, n)`` matrices of :func:`pack_upper`'s ``p``: its upper triangles, zero below the diagonal."""
    p = np.asarray(p)
    if p.shape[-1:] != (packed_size(n),):
        raise ValueError(f"unpack_upper: {p.shape} is not packed upper triangles of {n} x {n} matrices "
                         f"(last axis {packed_size(n)}): written by an mmflow that stored the squares? "
                         "Start that run afresh (--force)")
    out = np.zeros((*p.shape[:-1], n, n), p.dtype)
    i, j = np.triu_indices(n)
    out[..., i, j] = p
    return out


class NormalAccumulator:
    """Per-m accumulator of ``G_m`` and ``r_m`` for one frequency.

    ``G_m = sum_b B_b^H w_b B_b`` (one for every data split) and, for each data split ``s``
    (full, even, odd, ...), ``r_m[s] = sum_b B_b^H w_b v_b[s]`` and ``v^H W v[s]``: the
    splits share one transfer pass; each costs one extra column of the right-hand side GEMM.

    Parameters
    ----------
    lmax, mmax : int
    dtype : complex64 or complex128 (the Gram's precision)
    n_split : int, number of data vectors per m
    """

    def __init__(self, lmax, mmax, dtype=np.complex128, ms=None, n_split=1):
        self.lmax, self.mmax, self.n_split = lmax, mmax, n_split
        self.ms = list(range(mmax + 1)) if ms is None else list(ms)
        self.gram = {m: np.zeros((lmax - m + 1, lmax - m + 1), dtype, order="F") for m in self.ms}
        self.rhs = {m: np.zeros((n_split, lmax - m + 1), dtype) for m in self.ms}
        self.vhv = np.zeros((n_split, mmax + 1))
        self.dtype = np.dtype(dtype)

    def add_mmodes(self, m, block, mmodes, inv_var):
        """Add one chunk from its m-modes ``([n_split,] mmax + 1, 2, n_b)`` and weights ``(n_b,)``.

        The data vector and weights follow the block's rows: ``V_m`` then ``conj(V_{-m})`` for m > 0.
        Also accumulates ``v^H N^-1 v`` (for L-curves).
        """
        mm = mmodes if mmodes.ndim == 4 else mmodes[None]
        v = mm[:, m, 0] if m == 0 else np.concatenate([mm[:, m, 0], mm[:, m, 1]], axis=1)
        w = inv_var if m == 0 else np.concatenate([inv_var, inv_var])
        self.add(m, block, v, w)
        self.vhv[:, m] += np.sum(w * np.abs(v) ** 2, axis=1)

    def add(self, m, block, v=None, inv_var=None):
        """Add one chunk: ``G_m += B^H W B``, ``r_m += B^H W v`` with ``W = diag(inv_var)``.

        ``v``: ``(rows,)`` or ``(n_split, rows)``. ``block`` may have fewer columns than
        ``lmax - m + 1`` (a chunk of short baselines whose coefficients vanish beyond its
        lmax): only the leading sub-block is updated, which is where per-baseline lmax saves
        most of the Gram work.
        """
        b = np.asarray(block, self.dtype)
        n = b.shape[1]
        if inv_var is not None:
            b = b * np.sqrt(np.asarray(inv_var, float))[:, None].astype(b.real.dtype)
        if n == self.gram[m].shape[0]:
            self.gram[m] = herk_upper(b, self.gram[m])
        else:
            sub = np.asfortranarray(self.gram[m][:n, :n])
            self.gram[m][:n, :n] = herk_upper(b, sub)
        if v is not None:
            vv = np.atleast_2d(np.asarray(v, self.dtype))
            if inv_var is not None:
                vv = vv * np.sqrt(np.asarray(inv_var, float)).astype(vv.real.dtype)
            self.rhs[m][:, :n] += (b.conj().T @ vv.T).T

    def add_scaled_block(self, m, out, rows, ncols, vw=None, timings=None):
        """Add one transfer block given as ``out[l - m, c]`` (C-ordered, ``(L, lda)``), already weighted.

        ``G_m[:ncols, :ncols] += B^H B`` and ``r_m[:, :ncols] += B^H vw`` for ``B = out[:ncols, :rows]^T``
        (rows are baselines times ``sqrt(w)``, ``vw`` the data times ``sqrt(w)``, ``(n_split, rows)``).
        No copy of the Gram or of the block (:func:`herk_into`); one BLAS call each.
        """
        if m not in self.gram:
            return
        if out.dtype != self.dtype:
            out = np.ascontiguousarray(out, self.dtype)
        t0 = time.perf_counter()
        herk_into(self.gram[m], out, rows, ncols, out.shape[1])
        t1 = time.perf_counter()
        if vw is not None:
            # r[s, l] = sum_c conj(out[l, c]) vw[s, c]
            tmp = out[:ncols, :rows] @ np.conj(np.asarray(vw, self.dtype)).T
            self.rhs[m][:, :ncols] += tmp.conj().T
        if timings is not None:
            t2 = time.perf_counter()
            timings["herk_s"] = timings.get("herk_s", 0.0) + t1 - t0
            timings["rhs_s"] = timings.get("rhs_s", 0.0) + t2 - t1
            timings["herk_flops"] = timings.get("herk_flops", 0.0) + 4.0 * rows * ncols * (ncols + 1)

    def full_gram(self, m):
        return hermitian_full(self.gram[m])
