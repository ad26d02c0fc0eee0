"""The m-mode fit's traced peak against its cost model, over a grid of bins, band limits and mmax (JSON on stdout).

Runs :func:`mmflow.mmode.gapfill.chunk_mmodes` (splits full, even, odd; 128 baselines of random data with a gap of
8 % of the bins, so that the least-squares fit runs, not the plain transform:
:func:`mmflow.bench.gaps.traced_fit_bytes`) under ``tracemalloc`` at bins
512-2048, ``k_max`` from 3 % of the bins to a quarter of them (the largest the even / odd splits fit) and mmax
100 and 400, and prints each point's peak beside :func:`mmflow.workflow.stages.mmodes.cost.fit_bytes` and their
ratio. The constants of that function (``FIT_PHASES``, ``FIT_HELD_OUTPUTS``, ``FIT_STACKED_OUTPUTS``) were fitted
to these points (the largest relative error made least); ``tests/workflow/test_plan.py`` holds them at points
not among them.

Usage: ``python benchmarks/mmode_fit_memory.py``
"""
from __future__ import annotations

import json

import numpy as np

from mmflow.bench.gaps import traced_fit_bytes
from mmflow.workflow.stages.mmodes.cost import fit_bytes

SPLITS = ("full", "even", "odd")
N_BL = 128


def main():
    rng = np.random.default_rng(1)
    rows = []
    for n_bins in (512, 1024, 2048):
        for frac in (0.03, 0.06, 0.12, 0.25):
            k_max = int(frac * n_bins) - 1 if frac < 0.25 else n_bins // 4 - 1
            for mmax in (100, 400):
                peak = traced_fit_bytes(n_bins, k_max, mmax, N_BL, rng, SPLITS)
                counted = fit_bytes(n_bins, k_max, len(SPLITS), mmax, N_BL)
                rows.append({"n_bins": n_bins, "k_max": k_max, "mmax": mmax, "traced_mb": round(peak / 1e6, 3),
                             "counted_mb": round(counted / 1e6, 3), "counted/traced": round(counted / peak, 3)})
    ratios = [r["counted/traced"] for r in rows]
    print(json.dumps({"points": rows, "min_ratio": min(ratios), "max_ratio": max(ratios)}, indent=1))


if __name__ == "__main__":
    main()
