"""The packed upper triangles the stores hold Grams and Cholesky factors in (mmflow.mmode.normal)."""
import tracemalloc

import numpy as np
import pytest
import scipy.linalg as sla

from mmflow.mmode.normal import (hermitian_block, hermitian_full, pack_leading_upper, pack_upper, packed_size,
                                 unpack_upper, upper_block)


def _hermitian(rng, n, dtype=np.complex128):
    b = rng.normal(size=(2 * n, n)) + 1j * rng.normal(size=(2 * n, n))
    return (b.conj().T @ b + n * np.eye(n)).astype(dtype)


def test_packing_keeps_the_upper_triangle_and_nothing_else():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(3, 7, 7)) + 1j * rng.normal(size=(3, 7, 7))
    p = pack_upper(a)
    assert p.shape == (3, packed_size(7)) == (3, 28)
    assert p[0, 7] == a[0, 1, 1] and p[0, 1] == a[0, 0, 1]  # row by row: row 0 has 7 elements
    back = unpack_upper(p, 7)
    np.testing.assert_array_equal(back, np.triu(a))  # the strict lower triangle comes back as zeros
    np.testing.assert_array_equal(pack_upper(back), p)
    with pytest.raises(ValueError, match="squares"):  # a square store of an older layout is refused
        unpack_upper(a[0], 7)


def test_a_packed_gram_gives_readers_the_same_bits():
    """What hermitian_full makes of a Gram (its upper triangle: herk's output) is the same from the packed copy,
    in the stores' complex64 too."""
    rng = np.random.default_rng(2)
    g = np.triu(_hermitian(rng, 9, np.complex64))
    np.testing.assert_array_equal(hermitian_full(unpack_upper(pack_upper(g), 9)), hermitian_full(g))


def test_a_gram_block_is_the_full_matrix_of_its_packed_rows():
    """hermitian_block reads the leading n x n block of a packed n0 x n0 triangle (the solve stage's m of a
    block) as the square route does, ``hermitian_full(unpack_upper(p, n0)[:n, :n])``: the upper triangle's
    bits, its conjugate below, in complex128; a triangle of another size is refused."""
    rng = np.random.default_rng(4)
    for dtype in (np.complex64, np.complex128):
        g = np.triu(_hermitian(rng, 11, dtype))
        p = pack_upper(g)
        for n in (11, 7, 1, 0):
            block = hermitian_block(p, 11, n)
            assert block.dtype == np.complex128 and block.shape == (n, n)
            square = np.triu(unpack_upper(p, 11)[:n, :n].astype(np.complex128))
            np.testing.assert_array_equal(np.triu(block), square)
            np.testing.assert_array_equal(np.tril(block, -1), np.tril(square.conj().T, -1))
            np.testing.assert_array_equal(block, hermitian_full(unpack_upper(p, 11)[:n, :n]))
    with pytest.raises(ValueError, match="squares"):
        hermitian_block(p, 12, 5)
    with pytest.raises(ValueError, match="leading block of 12"):
        hermitian_block(p, 11, 12)


def test_a_gram_block_is_built_in_one_array():
    """The block is made in place: its traced peak is the one n x n complex128 array it returns (the square
    route held ~5 of them at once: the complex64 square, its complex128 copy, two triangles and their sum)."""
    rng = np.random.default_rng(5)
    p = pack_upper(np.triu(_hermitian(rng, 300, np.complex64)))
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        block = hermitian_block(p, 300, 290)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert block.nbytes <= peak < 1.05 * block.nbytes


def test_a_factors_corner_packs_and_unpacks_as_the_padded_square_does():
    """A kept corner (nk x nk) of an n0 x n0 factor: pack_leading_upper gives pack_upper of the zero-padded square
    and upper_block the square route's corner, ``unpack_upper(p, n0)[:nk, :nk]``, bit for bit; the factor's lower
    triangle (cho_factor's leftovers) is not stored."""
    rng = np.random.default_rng(6)
    for nk in (9, 5, 0):
        cho = rng.normal(size=(nk, nk)) + 1j * rng.normal(size=(nk, nk))  # lower triangle: garbage
        padded = np.zeros((9, 9), complex)
        padded[:nk, :nk] = cho
        out = np.full(packed_size(9), np.nan, complex)
        np.testing.assert_array_equal(pack_leading_upper(cho, 9, out), pack_upper(padded))
        np.testing.assert_array_equal(upper_block(out, 9, nk), unpack_upper(out, 9)[:nk, :nk])
        np.testing.assert_array_equal(upper_block(out, 9, nk), np.triu(cho))


def test_a_packed_factor_solves_to_the_same_bits():
    """cho_factor leaves the input's lower triangle in its factor; potrs reads the upper triangle only, so the
    packed factor (zeros below) solves to the factor's bits, a top-left corner as the CLEAN reads it too."""
    rng = np.random.default_rng(3)
    g = _hermitian(rng, 12)
    for n in (12, 8):
        cho, lower = sla.cho_factor(g[:n, :n].copy(), lower=False)
        assert np.abs(np.tril(cho, -1)).max() > 0  # the garbage the store no longer holds
        padded = np.zeros((12, 12), complex)
        padded[:n, :n] = cho
        stored = unpack_upper(pack_upper(padded), 12)[:n, :n]
        x = rng.normal(size=(n, 3)) + 1j * rng.normal(size=(n, 3))
        np.testing.assert_array_equal(sla.cho_solve((stored, False), x), sla.cho_solve((cho, lower), x))
