"""The paper's Table 1: one summary row per channel, as Markdown, CSV and JSON.

Columns: frequency and bandwidth (MHz); FWHM of the synthesised beam (major x minor, arcmin)
at declinations 0, +45 and +75 deg (from :func:`mmflow.imaging.psf.psf_table`); the jackknife
noise in K and mJy/beam (:mod:`mmflow.imaging.jackknife`); the fraction of singular values of
the transfer matrix above ``sqrt(eps)``, i.e. of Gram eigenvalues above ``eps``, counted over
all m blocks (:func:`fraction_of_modes`). Extra columns: the noise of every jackknife the
run's splits allow and the rms of the day/night systematics map (:data:`SPLIT_NOISE`).
"""
from __future__ import annotations

import csv
import io
import json

import numpy as np

from mmflow.imaging import psf as psf_mod

TABLE1_DECS_DEG = (0.0, 45.0, 75.0)


def fraction_of_modes(eigenvalues, eps):
    """``#{s_i > eps} / #{s_i}`` over every block's Gram eigenvalues (``sigma_i^2 = s_i``).

    ``eigenvalues``: iterable of per-m arrays (the kept coefficients of each block).
    """
    ev = [np.asarray(e) for e in eigenvalues]
    total = sum(len(e) for e in ev)
    return float(sum(int(np.sum(e > eps)) for e in ev) / total) if total else 0.0


def gram_eigenvalues(acc, ms=None, keep=None):
    """Eigenvalues of each block's Gram (restricted to ``keep(m)`` when given)."""
    out = []
    for m in (acc.ms if ms is None else ms):
        g = acc.full_gram(m)
        if keep is not None:
            k = keep(m)
            g = g[np.ix_(k, k)]
        out.append(np.linalg.eigvalsh(g))
    return out


SPLIT_NOISE = {"even_odd": "even/odd", "per_day": "per-day", "day_night": "day/night rms"}  # extra columns


def table1_row(freq_hz, bandwidth_hz, table, noise, fraction, by_split=None, decs_deg=TABLE1_DECS_DEG):
    """One row: ``table`` from :func:`psf.psf_table`, ``noise`` from :func:`jackknife.noise_summary`.

    ``by_split``: ``{kind: noise_summary}`` for the kinds of :data:`SPLIT_NOISE` the run's splits
    allow (even/odd and per-day jackknife sigmas, the rms of the day/night systematics map),
    each as extra columns ``noise_k_<kind>`` and ``noise_mjy_per_beam_<kind>`` after the paper's.
    """
    row = {"freq_mhz": freq_hz / 1e6, "bandwidth_mhz": bandwidth_hz / 1e6}
    for d in decs_deg:
        dec = np.deg2rad(d)
        row[f"fwhm_major_arcmin_dec{d:+.0f}"] = float(np.rad2deg(psf_mod.interp_table(table, dec, "major")) * 60)
        row[f"fwhm_minor_arcmin_dec{d:+.0f}"] = float(np.rad2deg(psf_mod.interp_table(table, dec, "minor")) * 60)
    row["noise_k"] = noise["kelvin"]
    row["noise_mjy_per_beam"] = noise["mjy_per_beam"]
    row["fraction_of_modes"] = fraction
    for kind in SPLIT_NOISE:
        if by_split and kind in by_split:
            row[f"noise_k_{kind}"] = by_split[kind]["kelvin"]
            row[f"noise_mjy_per_beam_{kind}"] = by_split[kind]["mjy_per_beam"]
    return row


def split_columns(rows):
    """``[(kind, label)]`` of the extra noise columns the rows carry (:data:`SPLIT_NOISE`)."""
    return [(k, label) for k, label in SPLIT_NOISE.items() if rows and f"noise_k_{k}" in rows[0]]


def _decs(rows):
    return [k[len("fwhm_major_arcmin_dec"):] for k in rows[0] if k.startswith("fwhm_major_arcmin_dec")]


def to_markdown(rows):
    """The table as the paper lays it out (FWHM as ``major' x minor'``)."""
    decs = _decs(rows)
    head = ["#", "nu (MHz)", "dnu (MHz)"] + [f"FWHM dec {d}" for d in decs] + \
        ["noise (K)", "noise (mJy/beam)", "fraction sigma > sqrt(eps)"] + \
        [f"{label} {unit}" for _, label in split_columns(rows) for unit in ("(K)", "(mJy/beam)")]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, r in enumerate(rows, 1):
        cells = [str(i), f"{r['freq_mhz']:.3f}", f"{r['bandwidth_mhz']:.3f}"]
        cells += [f"{r['fwhm_major_arcmin_dec' + d]:.1f}' x {r['fwhm_minor_arcmin_dec' + d]:.1f}'" for d in decs]
        cells += [f"{r['noise_k']:.0f}", f"{r['noise_mjy_per_beam']:.0f}", f"{r['fraction_of_modes']:.3f}"]
        cells += [f"{r[f'noise_{u}_{k}']:.0f}" for k, _ in split_columns(rows) for u in ("k", "mjy_per_beam")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def to_csv(rows):
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def to_json(rows):
    return json.dumps(rows, indent=1)
