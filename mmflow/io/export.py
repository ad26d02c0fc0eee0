"""FITS and PNG output (written under a temporary name, then renamed)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _tmp(path):
    path = Path(path)
    return path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")


def write_healpix_fits(path, hmap, meta):
    """HEALPix map (RING) with header keywords from ``meta``."""
    import healpy

    tmp = _tmp(path)
    healpy.write_map(str(tmp), np.asarray(hmap, np.float64), overwrite=True, coord=meta.get("COORDSYS", "C"),
                     column_units=meta.get("BUNIT", ""), extra_header=[(k[:8], v) for k, v in meta.items()
                                                                      if k not in ("COORDSYS",)], dtype=np.float64)
    os.replace(tmp, path)


def write_mollweide_png(path, hmap, title, unit):
    import healpy
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = np.percentile(hmap, [1, 99.5])
    healpy.mollview(hmap, title=title, unit=unit, min=lo, max=hi, cmap="inferno")
    healpy.graticule(dpar=30, dmer=30, alpha=0.3)
    tmp = _tmp(path)
    plt.savefig(tmp, dpi=110)
    plt.close("all")
    os.replace(tmp, path)


def write_lcurve_png(path, lc, eps, chosen):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    ax.loglog(np.sqrt(lc[:, 0]), np.sqrt(np.maximum(lc[:, 1], 1e-300)), "-")
    k = int(np.argmin(np.abs(np.log(eps / chosen))))
    ax.loglog([np.sqrt(lc[k, 0])], [np.sqrt(lc[k, 1])], "o", label=f"eps = {chosen:g}")
    ax.set_xlabel("||a||")
    ax.set_ylabel("||v - B a||")
    ax.legend()
    fig.tight_layout()
    tmp = _tmp(path)
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
