"""Figures of the science products (matplotlib, Agg): flux scale, spectral index, CLEAN history.

Each writer draws one PNG (written under a temporary name, then renamed) and returns what it
drew, so that tests and the report can check the figure's content without reading pixels.
The Mollweide projection used for RGB and for side-by-side panels is computed here
(:func:`mollweide_lonlat`); single maps with a colour bar use
:func:`mmflow.io.export.write_mollweide_png`.
"""
from __future__ import annotations

import os
import textwrap

import healpy
import matplotlib
import matplotlib.pyplot as plt  # healpy imports pyplot itself: no extra cost
import numpy as np

from mmflow.analysis.spectral_index import three_colour
from mmflow.io.export import tmp_sibling
from mmflow.sky.sources import CATALOG


def _pyplot():
    matplotlib.use("Agg")  # the backend is chosen where a PNG is drawn, never on import
    return plt


def _save(fig, path, plt, **kw):
    tmp = tmp_sibling(path)
    fig.savefig(tmp, dpi=100, **kw)
    plt.close(fig)
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- flux scale

def write_flux_scale_png(path, rows, epoch_year=None, catalog=None, ncols=4):
    """The paper's flux-scale figure: per source, measured map fluxes over its published spectrum.

    Parameters
    ----------
    rows : list of dict
        :func:`mmflow.analysis.fluxscale.flux_scale_rows` of every channel (``name``,
        ``freq_hz``, ``measured_jy``, optional ``measured_err_jy``).
    epoch_year : float, optional
        Epoch of the observation for secular spectra (Cas A).
    catalog : dict name -> :class:`mmflow.sky.sources.Source` (default: the built-in CATALOG).

    Returns
    -------
    dict with ``panels`` (source names in order), ``points`` (measured points drawn) and
    ``median_ratio`` per source (measured / spectrum).
    """
    catalog = CATALOG if catalog is None else catalog
    names = list(dict.fromkeys(r["name"] for r in rows))
    if not names:
        raise ValueError("no flux-scale rows to plot")
    plt = _pyplot()
    ncols = min(ncols, len(names))
    nrows = -(-len(names) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.3 * ncols, 2.8 * nrows), squeeze=False)
    freqs = np.array([r["freq_hz"] for r in rows], float)
    lo, hi = max(10e6, 0.8 * freqs.min()), 1.25 * freqs.max()
    grid = np.geomspace(lo, hi, 100)
    out = {"panels": names, "points": 0, "median_ratio": {}}
    for ax, name in zip(axes.ravel(), names):
        rs = [r for r in rows if r["name"] == name]
        f = np.array([r["freq_hz"] for r in rs]) / 1e6
        s = np.array([r["measured_jy"] for r in rs])
        err = np.array([r.get("measured_err_jy") or 0.0 for r in rs])
        src = catalog.get(name)
        if src is not None:
            model = np.asarray(src.flux(grid, epoch_year), float)
            ax.plot(grid / 1e6, model, "-", color="0.35", lw=1.2,
                    label=textwrap.fill(src.spectrum.reference or "spectrum", 34))
            out["median_ratio"][name] = float(np.median(s / np.asarray(src.flux(f * 1e6, epoch_year), float)))
        ax.errorbar(f, s, yerr=err if err.any() else None, fmt="o", ms=4, color="C3", label="this map")
        out["points"] += len(s)
        ax.set_xscale("log")
        if np.all(s > 0):
            ax.set_yscale("log")
        ratio = out["median_ratio"].get(name)
        ax.set_title(name + (f" (map / spectrum {ratio:.2f})" if ratio is not None else ""), fontsize=9)
        ax.set_xlabel("frequency (MHz)", fontsize=8)
        ax.set_ylabel("flux density (Jy)", fontsize=8)
        ax.minorticks_off()  # log axes' minor ticks are most of the drawing time of 14 panels
        ax.set_xticks(*_log_ticks(lo / 1e6, hi / 1e6))
        if ax.get_yscale() == "log":
            ax.set_yticks(*_log_ticks(*ax.get_ylim()))
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, loc="best")
    for ax in axes.ravel()[len(names):]:
        ax.set_visible(False)
    # fixed margins in inches (tight_layout would draw the 14-panel figure twice)
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=0.6 / w, right=1 - 0.15 / w, bottom=0.45 / h, top=1 - 0.3 / h, wspace=0.35, hspace=0.55)
    _save(fig, path, plt)
    return out


def _log_ticks(lo, hi, n=4):
    """About ``n`` 1-2-5 ticks between ``lo`` and ``hi`` (> 0) and their labels, for a log axis."""
    nice = np.array([d * 10.0**e for e in range(int(np.floor(np.log10(lo))) - 1, int(np.ceil(np.log10(hi))) + 1)
                     for d in (1, 2, 5)])
    inside = nice[(nice >= lo) & (nice <= hi)]
    if len(inside) < 2:  # less than a 1-2-5 step: rounded log-spaced values
        inside = np.unique([float(f"{v:.2g}") for v in np.geomspace(lo, hi, n)])
    step = max(1, len(inside) // n)
    ticks = inside[::step]
    return ticks, [f"{t:g}" for t in ticks]


# ----------------------------------------------------------------------------- Mollweide grids

def mollweide_lonlat(xsize=800):
    """Longitude and latitude (rad) of an ``xsize x xsize/2`` Mollweide image, NaN outside.

    Inverse Mollweide: ``x = 2 sqrt2 lon cos(t) / pi``, ``y = sqrt2 sin(t)``,
    ``2 t + sin 2t = pi sin(lat)``; longitude increases to the left (the sky seen from inside).
    Row 0 is the top (north).
    """
    ysize = xsize // 2
    x = (np.arange(xsize) + 0.5) / xsize * 4 * np.sqrt(2) - 2 * np.sqrt(2)
    y = np.sqrt(2) - (np.arange(ysize) + 0.5) / ysize * 2 * np.sqrt(2)
    gx, gy = np.meshgrid(x, y)
    t = np.arcsin(np.clip(gy / np.sqrt(2), -1, 1))
    lat = np.arcsin(np.clip((2 * t + np.sin(2 * t)) / np.pi, -1, 1))
    lon = -np.pi * gx / (2 * np.sqrt(2) * np.cos(t))
    inside = (gx / (2 * np.sqrt(2))) ** 2 + (gy / np.sqrt(2)) ** 2 <= 1
    return np.where(inside, lon, np.nan), np.where(inside, lat, np.nan)


def mollweide_pixels(nside, xsize=800):
    """HEALPix (RING) pixel of each Mollweide image sample, -1 outside the ellipse."""
    lon, lat = mollweide_lonlat(xsize)
    ok = np.isfinite(lon)
    pix = np.full(lon.shape, -1, int)
    pix[ok] = healpy.ang2pix(nside, np.pi / 2 - lat[ok], np.mod(lon[ok], 2 * np.pi))
    return pix


def _graticule(ax, xsize):
    lon_l = np.linspace(-np.pi, np.pi, 361)
    for lat0 in np.deg2rad([-60, -30, 0, 30, 60]):
        ax.plot(*_project(lon_l, np.full_like(lon_l, lat0), xsize), color="0.5", lw=0.4, alpha=0.6)
    lat_l = np.linspace(-np.pi / 2, np.pi / 2, 181)
    for lon0 in np.deg2rad(np.arange(-180, 181, 60)):
        ax.plot(*_project(np.full_like(lat_l, lon0), lat_l, xsize), color="0.5", lw=0.4, alpha=0.6)


def _project(lon, lat, xsize):
    """Forward Mollweide to image pixel coordinates (Newton for ``2t + sin 2t = pi sin lat``)."""
    t = lat.copy()
    for _ in range(30):
        t -= (2 * t + np.sin(2 * t) - np.pi * np.sin(lat)) / (2 + 2 * np.cos(2 * t) + 1e-12)
    x = -2 * np.sqrt(2) * lon * np.cos(t) / np.pi
    y = np.sqrt(2) * np.sin(t)
    return (x + 2 * np.sqrt(2)) / (4 * np.sqrt(2)) * xsize - 0.5, (np.sqrt(2) - y) / (2 * np.sqrt(2)) * (
        xsize // 2
    ) - 0.5


# ----------------------------------------------------------------------------- spectral index

def write_three_colour_png(path, maps, freqs_hz, mask=None, index=2.5, title=None, frame="galactic", xsize=800):
    """Three-colour Mollweide of three channels scaled by ``nu^index`` (red: lowest frequency).

    Colours from :func:`mmflow.analysis.spectral_index.three_colour`: a spectrum
    ``T ~ nu^-index`` is grey-white, flatter spectra blue, steeper red. Pixels outside ``mask``
    (never observed) are mid-grey, outside the ellipse white.

    Returns
    -------
    dict with ``rgb`` (the projected image, (ysize, xsize, 3) floats) and ``freqs_mhz``.
    """
    freqs = np.asarray(freqs_hz, float)
    if len(maps) != 3 or len(freqs) != 3:
        raise ValueError("a three-colour image needs exactly three maps and three frequencies")
    order = np.argsort(freqs)  # red = lowest frequency
    nside = healpy.npix2nside(len(maps[0]))
    ok = np.ones(len(maps[0]), bool) if mask is None else np.asarray(mask, bool).copy()
    for m in maps:
        ok &= np.isfinite(m) & (np.asarray(m) != healpy.UNSEEN)
    rgb_pix = np.full((len(ok), 3), np.nan)
    rgb_pix[ok] = three_colour([np.asarray(maps[i], float)[ok] for i in order], freqs[order], index)
    pix = mollweide_pixels(nside, xsize)
    img = np.ones(pix.shape + (3,))
    inside = pix >= 0
    img[inside] = np.where(ok[pix[inside]][:, None], rgb_pix[pix[inside]], 0.5)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(10, 5.6))
    ax.imshow(img, interpolation="nearest")
    _graticule(ax, xsize)
    ax.set_axis_off()
    f = freqs[order] / 1e6
    ax.set_title(title or f"{frame}: R {f[0]:.3f}, G {f[1]:.3f}, B {f[2]:.3f} MHz, scaled by nu^{index:g} "
                 f"(white: T ~ nu^-{index:g})", fontsize=10)
    _save(fig, path, plt, bbox_inches="tight")
    return {"rgb": img, "freqs_mhz": f.tolist()}


def write_spectral_index_png(path, beta, r2, nu1_hz, nu2_hz, beta_range=(-3.0, -2.0), r2_min=0.0, frame="galactic",
                             xsize=600):
    """Two Mollweide panels: the T-T spectral index ``beta`` and its ``R^2``.

    ``beta`` is drawn where ``R^2 >= r2_min`` (grey elsewhere and where NaN); inputs are
    :func:`mmflow.analysis.spectral_index.local_tt`'s HEALPix maps.

    Returns
    -------
    dict with ``beta_median``, ``r2_median`` (over the drawn pixels) and ``drawn_fraction``.
    """
    beta, r2 = np.asarray(beta, float), np.asarray(r2, float)
    nside = healpy.npix2nside(len(beta))
    pix = mollweide_pixels(nside, xsize)
    show = np.isfinite(beta) & np.isfinite(r2) & (r2 >= r2_min)
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    for ax, values, label, rng, cmap in ((axes[0], np.where(show, beta, np.nan), "spectral index beta", beta_range,
                                          "RdYlBu_r"), (axes[1], r2, "R^2 of the T-T fit", (0, 1), "viridis")):
        img = np.full(pix.shape, np.nan)
        img[pix >= 0] = values[pix[pix >= 0]]
        cm = plt.get_cmap(cmap).copy()
        cm.set_bad("0.6")
        im = ax.imshow(np.ma.masked_invalid(np.where(pix >= 0, img, np.nan)), cmap=cm, vmin=rng[0], vmax=rng[1],
                       interpolation="nearest")
        outside = np.where(pix < 0, 1.0, np.nan)
        ax.imshow(np.ma.masked_invalid(outside), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        _graticule(ax, xsize)
        ax.set_axis_off()
        ax.set_title(f"{label} ({frame})", fontsize=10)
        fig.colorbar(im, ax=ax, orientation="horizontal", fraction=0.05, pad=0.04)
    fig.suptitle(f"T-T between {nu1_hz / 1e6:.3f} and {nu2_hz / 1e6:.3f} MHz"
                 + (f"; beta shown where R^2 >= {r2_min:g}" if r2_min > 0 else ""), fontsize=10)
    _save(fig, path, plt, bbox_inches="tight")
    return {"beta_median": float(np.median(beta[show])) if show.any() else float("nan"),
            "r2_median": float(np.nanmedian(r2)) if np.isfinite(r2).any() else float("nan"),
            "drawn_fraction": float(show.mean())}


# ----------------------------------------------------------------------------- CLEAN history

def write_clean_history_png(path, histories, threshold=None, unit="Jy/sr"):
    """Residual peak and cumulative components against major cycle, one line per channel.

    ``histories``: dict label -> list of per-cycle dicts with ``peak`` and optionally
    ``components`` (added that cycle); ``threshold``: dict label -> stop threshold (dashed).
    Returns ``{"lines": labels, "cycles": {label: n}}``.
    """
    plt = _pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    out = {"lines": [], "cycles": {}}
    for i, (label, rows) in enumerate(histories.items()):
        cyc = np.arange(len(rows))
        peak = np.array([abs(float(r["peak"])) for r in rows])
        a1.semilogy(cyc, np.maximum(peak, 1e-300), "-o", ms=2, color=f"C{i % 10}", label=str(label))
        if threshold and label in threshold:
            a1.axhline(threshold[label], ls="--", lw=0.8, color=f"C{i % 10}")
        if rows and "components" in rows[0]:
            a2.plot(cyc, np.cumsum([int(r["components"]) for r in rows]), "-", color=f"C{i % 10}", label=str(label))
        out["lines"].append(label)
        out["cycles"][label] = len(rows)
    a1.set_xlabel("major cycle")
    a1.set_ylabel(f"largest |residual| ({unit})")
    a1.set_title("residual peak (dashed: stop threshold)", fontsize=10)
    a2.set_xlabel("major cycle")
    a2.set_ylabel("components (cumulative)")
    a2.set_title("CLEAN components", fontsize=10)
    for a in (a1, a2):
        a.grid(True, alpha=0.2)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path, plt)
    return out
