"""Fixed-order reductions: the same bits for any cluster size, worker count or task order."""
from __future__ import annotations

import numpy as np


def ordered_tree_sum(parts):
    """Pairwise sum of ``parts`` in a fixed tree: ``((p0 + p1) + (p2 + p3)) + ...``.

    The tree depends only on ``len(parts)``, so floating-point results are bit-identical
    whichever worker computed which part and in whichever order they finished. Pairwise
    summation also bounds the rounding error by ``O(log n)`` instead of ``O(n)``.
    ``parts`` may be any iterable of equally shaped arrays (consumed lazily, holding at most
    ``log2(n) + 1`` partial sums).
    """
    stack = []  # (level, array)
    for p in parts:
        node = (0, np.array(p, copy=True))
        while stack and stack[-1][0] == node[0]:
            level, left = stack.pop()
            node = (level + 1, left + node[1])
        stack.append(node)
    if not stack:
        raise ValueError("nothing to sum")
    level, total = stack.pop()
    while stack:
        _, left = stack.pop()
        total = left + total
    return total
