"""FITS and PNG output (written under a temporary name, then renamed).

Maps mark the sky the array never sees (see :mod:`mmflow.imaging.sky_mask`): HEALPix
``UNSEEN`` in FITS, grey in PNGs. PNGs use a symmetric-logarithmic colour scale (linear
within +-linthresh, logarithmic beyond; stated on the colour bar), so that the Galactic
plane and the faint high-latitude sky both show, and carry lmax, eps, frequency and
resolution in a caption.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import healpy
import matplotlib
import matplotlib.pyplot as plt  # healpy imports pyplot itself: no extra cost
import numpy as np
from astropy.io import fits
from healpy.newvisufunc import projview

from mmflow.analysis import table1
from mmflow.imaging.lcurve import lcurve_corner

#: Header keywords of every polarised map: IAU (1974) Stokes parameters, the polarisation angle
#: from north through east and V > 0 for the field turning from north through east as the
#: receiver sees it, with the coherency ``[[I + Q, U - iV], [U + iV, I - Q]]`` on (north, east)
#: under mmflow's fringe (:func:`mmflow.conventions.stokes_coherency`; docs/conventions.md).
POLARISATION_KEYWORDS = {"POLCCONV": "IAU", "POLANGLE": "from north through east",
                         "VSIGN": "IAU: V>0 E turns N through E seen by receiver"}


def tmp_sibling(path):
    """A hidden per-process temporary file beside ``path``: written there, then renamed onto ``path``."""
    path = Path(path)
    return path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")


def _masked(hmap, mask):
    out = np.array(hmap, np.float64, copy=True)
    if mask is not None:
        out[..., ~np.asarray(mask, bool)] = healpy.UNSEEN
    return out


def write_healpix_fits(path, hmap, meta, mask=None, column_names=None):
    """HEALPix map (RING) with header keywords from ``meta``; pixels outside ``mask`` are UNSEEN.

    Parameters
    ----------
    hmap : ndarray ``(npix,)`` or ``(n_maps, npix)`` (one column per map, e.g. I, Q, U, V)
    mask : ndarray of bool, optional
        True where the sky was observed (:func:`mmflow.imaging.sky_mask.observed_sky_mask`).
    column_names : list of str, optional
        Names of the columns (healpy's default otherwise).
    """
    tmp = tmp_sibling(path)
    healpy.write_map(str(tmp), _masked(hmap, mask), overwrite=True, coord=meta.get("COORDSYS", "C"),
                     column_units=meta.get("BUNIT", ""), column_names=column_names,
                     extra_header=[(k[:8], v) for k, v in meta.items() if k not in ("COORDSYS",)], dtype=np.float64)
    os.replace(tmp, path)


def symlog_scale(values, lo_pct=0.5, hi_pct=99.9):
    """``(vmin, vmax, linthresh)`` of a symmetric-log colour scale for the observed pixels.

    ``vmin, vmax`` are percentiles (outliers saturate); ``linthresh``, the half-width of the
    linear part, is the median absolute deviation about the median: the faint sky's
    fluctuations fill the linear part and the Galactic plane the logarithmic decades.
    """
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return -1.0, 1.0, 1.0
    lo, hi = np.percentile(v, [lo_pct, hi_pct])
    mad = float(np.median(np.abs(v - np.median(v))))
    span = max(abs(lo), abs(hi), 1e-30)
    linthresh = mad if mad > 1e-6 * span else 1e-3 * span
    linthresh = float(f"{linthresh:.1g}")  # one significant figure: round tick values
    if hi <= lo:
        lo, hi = lo - linthresh, hi + linthresh
    return float(lo), float(hi), float(linthresh)


def symlog_ticks(vmin, vmax, linthresh):
    """Colour-bar ticks: 0, +-linthresh and each decade of linthresh inside ``[vmin, vmax]``."""
    ticks = [0.0] if vmin <= 0 <= vmax else []
    k = 0
    while linthresh * 10 ** k <= max(abs(vmin), abs(vmax)):
        ticks += [t for t in (linthresh * 10 ** k, -linthresh * 10 ** k) if vmin <= t <= vmax]
        k += 1
    return sorted(ticks)


AXIS_NAMES = {"galactic": ("Galactic longitude l", "Galactic latitude b"),
              "icrs": ("right ascension (ICRS)", "declination (ICRS)"),
              "date": ("right ascension (of date)", "declination (of date)")}


def caption_text(lmax=None, eps=None, freq_hz=None, resolution_deg=None, frame=None, masked=False):
    """``'40.000 MHz | lmax 64 | eps 0.01 | resolution 2.8 deg | ...'`` from what is known."""
    parts = []
    if freq_hz is not None:
        parts.append(f"{freq_hz / 1e6:.3f} MHz")
    if lmax is not None:
        parts.append(f"lmax {lmax}")
    if eps is not None:
        parts.append(f"eps {eps:g}")
    if resolution_deg is None and lmax:
        resolution_deg = 180.0 / lmax
    if resolution_deg is not None:
        parts.append(f"resolution {resolution_deg:.2g} deg")
    if frame is not None:
        parts.append(f"{frame} frame")
    text = " | ".join(parts)
    if masked:
        text += "\ngrey: sky never above the horizon. Monopole and m = 0 removed: the mean is not measured, " \
                "maps go negative."
    return text


def write_mollweide_png(path, hmap, title, unit, mask=None, lmax=None, eps=None, freq_hz=None,
                        resolution_deg=None, frame=None, xsize=1000):
    """Mollweide view: never-seen sky grey, labelled graticule, symmetric-log colour bar, caption.

    Parameters
    ----------
    hmap : ndarray
        HEALPix map (RING).
    title, unit : str
        Plot title; unit of the map (the colour bar states it and the scaling).
    mask : ndarray of bool, optional
        True where observed; other pixels are drawn grey and ignored by the colour scale.
    lmax, eps, freq_hz, resolution_deg, frame : optional
        Written in the caption (resolution defaults to 180 deg / lmax).
    xsize : int
        Longitude samples of the projected image (drawing time grows as xsize^2).

    Returns
    -------
    dict
        ``vmin, vmax, linthresh`` of the colour scale, ``colorbar_label``, ``caption`` and
        ``masked_fraction``.
    """
    matplotlib.use("Agg")  # the backend is chosen where a PNG is drawn, never on import
    shown = _masked(hmap, mask)
    seen = shown[shown != -1.6375e30]
    vmin, vmax, lin = symlog_scale(seen)
    label = f"{unit}; symmetric log scale, linear within +-{lin:.3g}"
    caption = caption_text(lmax, eps, freq_hz, resolution_deg, frame, masked=mask is not None and not np.all(mask))
    xlab, ylab = AXIS_NAMES.get(frame, ("longitude", "latitude"))
    fig = plt.figure(figsize=(10, 6.4))
    # projview ends with plt.draw(), a full render of the figure that savefig renders again
    fig.canvas.draw_idle = lambda *args, **kwargs: None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        projview(shown, fig=fig, xsize=xsize, title=title, unit=label, min=vmin, max=vmax, norm="symlog",
                 norm_dict={"linthresh": lin, "linscale": 1.0}, cmap="inferno", badcolor="0.6", bgcolor="white",
                 graticule=True, graticule_labels=True, longitude_grid_spacing=60, latitude_grid_spacing=30,
                 xlabel=f"{xlab} (deg)", ylabel=f"{ylab} (deg)", cb_orientation="horizontal",
                 cbar_ticks=symlog_ticks(vmin, vmax, lin), format="%.2g", hold=True)
    fig.text(0.5, 0.01, caption, ha="center", va="bottom", fontsize=9)
    drawn = [t for ax in fig.axes for t in (ax.get_xlabel(), ax.get_ylabel()) if "scale" in t]
    tmp = tmp_sibling(path)
    fig.savefig(tmp, dpi=100, bbox_inches="tight")
    plt.close(fig)
    os.replace(tmp, path)
    frac = 0.0 if mask is None else float(1 - np.mean(np.asarray(mask, bool)))
    return {"vmin": vmin, "vmax": vmax, "linthresh": lin, "colorbar_label": drawn[0] if drawn else None,
            "caption": caption, "masked_fraction": frac}


def write_lcurve_png(path, lc, eps, chosen, corner=None, freq_hz=None, weighted=False, unit="Jy/sr"):
    """The L-curve ``(||v - B a||, ||a||)`` over the trial eps, with the chosen eps and the corner.

    Parameters
    ----------
    lc : ndarray (n_eps, 2)
        ``||a||^2`` and ``||v - B a||^2`` summed over m (:func:`mmflow.imaging.lcurve.lcurve_block`).
    eps : ndarray (n_eps,)
        The trial regularisation parameters.
    chosen : float
        The eps used for the map.
    corner : float, optional
        The eps of maximum curvature (default: :func:`mmflow.imaging.lcurve.lcurve_corner`).
    freq_hz : float, optional
        Written in the title.
    weighted : bool
        True when the normal equations were noise weighted (``transfer.noise_weighting``):
        the residual is then in units of the noise (dimensionless), otherwise in Jy.
    unit : str
        Unit of the a_lm (Jy/sr).

    Returns
    -------
    float
        ``chosen / corner``: how far (as a factor) the chosen eps is from the corner.
    """
    matplotlib.use("Agg")  # the backend is chosen where a PNG is drawn, never on import
    lc = np.asarray(lc, float)
    eps = np.asarray(eps, float)
    if corner is None:
        corner = lcurve_corner(lc[:, 0], lc[:, 1], eps)
    sol, res = np.sqrt(np.maximum(lc[:, 0], 1e-300)), np.sqrt(np.maximum(lc[:, 1], 1e-300))
    fig, ax = plt.subplots(figsize=(6, 4.6))
    ax.loglog(res, sol, "-", color="0.3", lw=1.2, label=f"{len(eps)} trial eps ({eps.min():.0e} to {eps.max():.0e})")
    for value, style, name in ((chosen, "o", "chosen"), (corner, "x", "corner (max curvature)")):
        k = int(np.argmin(np.abs(np.log(eps / value))))
        ax.loglog([res[k]], [sol[k]], style, ms=9, mew=2, label=f"{name}: eps = {value:.3g}")
    ax.set_xlabel("residual norm ||N^-1/2 (v - B a)|| (noise units)" if weighted else "residual norm ||v - B a|| (Jy)")
    ax.set_ylabel(f"solution norm ||a|| ({unit})")
    ratio = float(chosen / corner)
    title = "L-curve" + (f" at {freq_hz / 1e6:.3f} MHz" if freq_hz is not None else "")
    ax.set_title(f"{title}\nchosen eps / corner eps = {ratio:.3g}", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.2)
    fig.tight_layout()
    tmp = tmp_sibling(path)
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
    return ratio


def write_image_fits(path, image, header):
    """A 2-D image (``image[y, x]``) with header keywords (WCS included) from ``header``."""
    hdu = fits.PrimaryHDU(np.asarray(image, np.float64))
    for k, v in header.items():
        hdu.header[k[:8]] = v
    tmp = tmp_sibling(path)
    hdu.writeto(tmp, overwrite=True)
    os.replace(tmp, path)


def psf_stamp_header(dec_deg, pixel_deg, n, meta):
    """WCS of a PSF stamp: azimuthal-equidistant (``ARC``) about ``(RA 0, dec)`` of date,
    RA increasing to the left (``CDELT1 < 0``), plus ``meta`` keywords."""
    c = (n + 1) / 2.0
    return {"CTYPE1": "RA---ARC", "CTYPE2": "DEC--ARC", "CRVAL1": 0.0, "CRVAL2": float(dec_deg),
            "CRPIX1": c, "CRPIX2": c, "CDELT1": -float(pixel_deg), "CDELT2": float(pixel_deg),
            "CUNIT1": "deg", "CUNIT2": "deg", **meta}


def write_psf_png(path, stamps, titles, half_width_deg, caption=""):
    """PSF stamps side by side (linear scale, peak 1, contours at 0.5 and 0), offsets in degrees.

    ``stamps``: list of ``image[y, x]`` (x east to the left, as on the sky), each ``2
    half_width_deg`` across.
    """
    matplotlib.use("Agg")  # the backend is chosen where a PNG is drawn, never on import
    fig, axes = plt.subplots(1, len(stamps), figsize=(4.2 * len(stamps), 4.4), squeeze=False)
    for ax, img, title, hw in zip(axes[0], stamps, titles, half_width_deg):
        img = np.asarray(img, float)
        ext = [hw, -hw, -hw, hw]  # east to the left
        im = ax.imshow(img, origin="lower", extent=ext, cmap="RdBu_r", vmin=-1, vmax=1)
        ax.contour(img, levels=[0.0, 0.5], colors=["0.4", "k"], linewidths=[0.6, 1.0], origin="lower", extent=ext)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("east offset (deg)")
        ax.set_ylabel("north offset (deg)")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="PSF / peak")
    if caption:
        fig.text(0.5, 0.005, caption, ha="center", va="bottom", fontsize=8)
    tmp = tmp_sibling(path)
    fig.savefig(tmp, dpi=90, bbox_inches="tight")
    plt.close(fig)
    os.replace(tmp, path)


def write_table1(directory, rows):
    """Table 1 as ``table1.md``, ``table1.csv`` and ``table1.json`` in ``directory``; returns the paths."""
    out = []
    for name, text in (("table1.md", table1.to_markdown(rows)), ("table1.csv", table1.to_csv(rows)),
                       ("table1.json", table1.to_json(rows))):
        path = Path(directory) / name
        tmp = tmp_sibling(path)
        tmp.write_text(text)
        os.replace(tmp, path)
        out.append(path)
    return out


def write_per_integration(uv, directory, fmt="ms", times=None, phase_frame="icrs"):
    """Write a pyuvdata ``UVData`` as one file per integration, as the OVRO-LWA writes
    MeasurementSets (``int_0000.<fmt>``, ...; ``times``: those integrations only).

    MS and uvfits cannot hold unprojected data: each file is phased to the zenith of its
    integration (``phase_to_time``, as ``write_ms(force_phase=True)`` does), as the OVRO-LWA's
    own files are (they use ``phase_frame="fk5"``, J2000); UVH5 keeps the drift scan as it is.
    Each file's rows are selected from a metadata-only copy and given their slice of the data
    (``select(inplace=False)`` would deep-copy every integration's data for each file). ``uv`` is
    checked once (``UVData.check``); the files' selections and writes skip pyuvdata's own check of
    every part (a deep copy of it each, a quarter of the time of a small file).
    Returns the paths.
    """
    uv.check()
    times = np.unique(uv.time_array) if times is None else times
    meta = uv.copy(metadata_only=True)
    paths = []
    for k, t in enumerate(times):
        rows = np.flatnonzero(np.isclose(uv.time_array, t, rtol=0, atol=uv._time_array.tols[1]))
        part = meta.select(blt_inds=rows, inplace=False, run_check=False)
        part.data_array, part.flag_array, part.nsample_array = (uv.data_array[rows], uv.flag_array[rows],
                                                                uv.nsample_array[rows])
        path = Path(directory) / f"int_{k:04d}.{fmt}"
        if fmt in ("ms", "uvfits"):
            part.phase_to_time(float(t), phase_frame=phase_frame)
        if fmt == "ms":
            part.write_ms(str(path), clobber=True, run_check=False)
        elif fmt == "uvfits":
            part.write_uvfits(str(path), run_check=False)
        else:
            part.write_uvh5(str(path), clobber=True, run_check=False)
        paths.append(path)
    return paths
