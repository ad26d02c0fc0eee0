"""The ingest plan's row checks at scale: duplicated (time, baseline) rows refused whether or not the
rows form pyuvdata's regular grid (the O(rows) path), and the distinct antenna pairs of a file."""
import numpy as np
import pytest

from mmflow.errors import InputError
from mmflow.io.checks import distinct_pairs, duplicate_rows


def _grid(n_ant=12, n_time=5):
    pairs = np.array([(i, j) for i in range(n_ant) for j in range(i, n_ant)])
    jd = np.repeat(2457802.0 + np.arange(n_time) * 13.0 / 86400, len(pairs))
    return jd, np.tile(pairs[:, 0], n_time), np.tile(pairs[:, 1], n_time), pairs


def test_a_regular_grid_passes_and_every_kind_of_repeat_is_named():
    jd, a1, a2, pairs = _grid()
    nb = len(pairs)
    duplicate_rows(jd, a1, a2, "f")  # the grid: no repeat
    duplicate_rows(jd, a2, a1, "f")  # conjugated orientation alike
    rng = np.random.default_rng(3)
    perm = rng.permutation(len(jd))
    duplicate_rows(jd[perm], a1[perm], a2[perm], "f")  # shuffled: the sorting path

    b1, b2 = a1.copy(), a2.copy()  # one baseline twice in the third integration, (j, i) written
    b1[2 * nb + 7], b2[2 * nb + 7] = a2[2 * nb + 8], a1[2 * nb + 8]
    with pytest.raises(InputError, match=rf"1 duplicated \(time, baseline\) rows: rows {2 * nb + 7} and {2 * nb + 8}"):
        duplicate_rows(jd, b1, b2, "f")
    t = jd.copy()  # the fourth integration's time repeats the second's: every baseline twice
    t[3 * nb:4 * nb] = jd[nb]
    with pytest.raises(InputError, match=rf"{nb} duplicated"):
        duplicate_rows(t, a1, a2, "f")


def test_distinct_pairs_are_numpys_unique_rows():
    jd, a1, a2, pairs = _grid()
    rng = np.random.default_rng(4)
    perm = rng.permutation(len(jd))
    got = np.stack(distinct_pairs(a1[perm] + 100, a2[perm] + 100), 1)
    assert np.array_equal(got, np.unique(np.stack([a1, a2], 1) + 100, axis=0))
    assert np.array_equal(got - 100, pairs)


def test_distinct_rows_read_off_the_grid_equal_those_of_every_row():
    """A grid's distinct times and pairs come from its first block; shuffled rows (no grid) give the same,
    and a grid with a repeat is refused like duplicate_rows."""
    from mmflow.io.checks import distinct_rows

    jd, a1, a2, pairs = _grid()
    times, p1, p2 = distinct_rows(jd, a1, a2, "f")
    perm = np.random.default_rng(5).permutation(len(jd))
    times_s, q1, q2 = distinct_rows(jd[perm], a1[perm], a2[perm], "f")
    assert np.array_equal(times, np.unique(jd)) and np.array_equal(times_s, times)
    assert np.array_equal(np.stack([p1, p2], 1), pairs) and np.array_equal(np.stack([q1, q2], 1), pairs)
    t = jd.copy()
    t[3 * len(pairs):4 * len(pairs)] = jd[len(pairs)]
    with pytest.raises(InputError, match=rf"{len(pairs)} duplicated"):
        distinct_rows(t, a1, a2, "f")
