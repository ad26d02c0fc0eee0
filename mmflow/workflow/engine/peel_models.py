"""What the ``peel`` store holds, read back: the sources' models (the ``models`` stage's fitted
components, copied into ``peel.zarr``'s attributes) and the visibilities of the removed and modelled
sources. The peel stage's tasks and its ``apply`` and the ``terrestrial`` stage use it; it reads only
``models.zarr`` / ``peel.zarr`` and the beam (as the telescope does), never the rest of the configuration.

Four correlations (:func:`four_correlation_jones`: ``vis.zarr`` holds xx, yy and the cross hands xy, yx,
and the beam is an E-field beam): the models are the sources' four correlations through the E-field
beam (:func:`mmflow.calibrate.coherency.source_correlations`), each parallel hand through its own
feed's beam, and the cross hands carry ``c_s h_ix conj(h_jy) M_xy`` (``conj(c_s)`` on yx) with the
complex coefficients ``peel.zarr``'s ``cross_scale`` holds (:mod:`mmflow.calibrate.cross_hands`).
"""
from __future__ import annotations

import json
from functools import lru_cache, partial

import numpy as np

from mmflow.calibrate.coherency import source_coherencies, source_correlations
from mmflow.calibrate.cross_hands import cross_model, gain_templates
from mmflow.calibrate.peel import MODEL, PEEL
from mmflow.errors import InputError
from mmflow.telescope.beam_factory import JONES_TYPES, make_jones
from mmflow.calibrate.source_models import GaussianComponent
from mmflow.simulate.corrupt import gain_products
from mmflow.sky.sources import Source, get_sources
from mmflow.io.run_stores import STORES


#: the correlations of a four-correlation peel (``peel.zarr``'s attribute ``correlations``)
FOUR = ["xx", "yy", "xy", "yx"]


def four_correlation_jones(ctx):
    """The E-field beam when the run's data hold the four linear correlations (``vis.zarr``'s ``pols``
    xx, yy and ``cross_pols`` xy, yx) and ``beam`` is an E-field beam: the peel and terrestrial stages
    then model and remove their components in all four (full-Stokes imaging reads them). None otherwise
    (a scalar beam, or data without cross hands): the parallel hands alone, as before."""
    attrs = ctx.vis_attrs()
    if list(attrs.get("pols", [])) != FOUR[:2] or list(attrs.get("cross_pols") or []) != FOUR[2:]:
        return None
    if ctx.cfg.beam.type not in JONES_TYPES:
        return None
    return _jones(ctx.cfg.beam.model_dump_json())


@lru_cache(maxsize=4)
def _jones(beam_json):
    try:
        return make_jones(json.loads(beam_json))
    except InputError:  # a pyuvdata power beam: no feeds to model
        return None


def fitted_tables(g, names):
    """``{source: per channel a list of component rows (MODEL_COLUMNS)}`` of ``models.zarr`` (group ``g``)
    for the fitted sources among ``names``: what the peel stage copies into ``peel.zarr``'s attributes,
    so that its ``apply`` (run by any later reader) needs no other store."""
    order = list(g.attrs["sources"])
    table = g[STORES.models.components][:]  # (freq, source, component, column): small
    return {n: [[[float(x) for x in row] for row in table[fi, order.index(n)] if row[2] != 0]
                for fi in range(table.shape[0])] for n in order if n in names}


def fitted_sources(ctx, fi, names):
    """Catalogue sources ``names`` for channel ``fi``, those the models stage fitted (``peel.zarr``'s
    attribute ``fitted_models``) with their fitted components. Reads only ``peel.zarr``."""
    srcs = get_sources(list(names))
    fitted = ctx.open(STORES.peel).attrs.get("fitted_models", {})
    out = []
    for s in srcs:
        if s.name not in fitted:
            out.append(s)
            continue
        comps = [GaussianComponent(*row) for row in fitted[s.name][fi]]
        tot = sum(c.flux_jy for c in comps)
        out.append(Source(s.name, s.ra_deg, s.dec_deg, s.spectrum, [c.as_source_component(tot) for c in comps]))
    return out


def peel_coherencies(ctx, tel, fi, lst, pairs, names, dtype=np.complex128, jones=None):
    """(n_src, time, bl) model visibilities of sources ``names`` in channel ``fi`` at the data's epoch
    (the models stage's fitted components for the sources ``peel.zarr`` lists as ``fitted_models``,
    :func:`fitted_sources`); 0 at integrations without an LST (missing). ``dtype``: the working
    precision and the result's (complex64 for the peel solve, which runs in single precision).
    With ``jones`` (:func:`four_correlation_jones`): (n_src, time, bl, 4), xx, yy, xy, yx through it."""
    good = np.isfinite(lst)
    out = np.zeros((len(names), len(lst), len(pairs)) + ((4,) if jones is not None else ()), dtype)
    if good.any():
        args = (tel, float(tel.freqs_hz[fi]), lst[good], fitted_sources(ctx, fi, names),
                float(ctx.vis_attrs()["epoch_jd"]), pairs, dtype)
        model = source_coherencies if jones is None else partial(source_correlations, jones=jones)
        if good.all():
            model(*args, out=out)  # filled in place: no copy of the sources' stack
        else:
            out[:, good] = model(*args)
    return out


def peel_components(ctx, block, fi, kinds, cross=False):
    """``sum_s f_s(t) h_si conj(h_sj) M^s_ij`` (time, bl, pol) of channel ``fi`` (of ``vis.zarr``) over the
    sources whose mode is in ``kinds``, ``f`` being 1 (peeled) or the fitted scale (subtracted,
    modelled); only the sources with such a mode somewhere in the block are computed. Reads only
    ``peel.zarr`` (and the beam). Returns ``(parallel, cross)``: with ``cross`` also the cross hands
    (time, bl, 2) of the same sources, ``sum_s c_s(t) T^s`` (:mod:`mmflow.calibrate.cross_hands`), which a
    four-correlation peel (``peel.zarr``'s ``correlations``) holds; else ``cross`` is None."""
    tel = ctx.telescope()
    attrs = ctx.open(STORES.peel).attrs
    names = attrs["sources"]
    four = attrs.get("correlations") == FOUR
    if cross and not four:
        raise InputError(str(ctx.run.store(STORES.peel)), "correlations", "the peel solutions hold the parallel "
                         "hands only, and this stage reads the cross hands too: they would keep what peeling "
                         "removed", "rerun the peel stage with an E-field beam on data holding xy, yx (--force)")
    region = (block.rows, slice(fi, fi + 1))
    mode = ctx.read(STORES.peel.mode, region)[:, 0]  # (time, src, pol)
    out = np.zeros(block.vis.shape[:2] + block.vis.shape[3:], complex)  # (time, bl, pol)
    out_cross = np.zeros(block.vis.shape[:2] + (2,), complex) if cross else None
    used = [s for s in range(len(names)) if np.isin(mode[:, s], kinds).any()]
    if not used:
        return out, out_cross
    scale = ctx.read(STORES.peel.scale, region)[:, 0]
    h = ctx.read(STORES.peel.dd_gains, region)[:, 0]  # (time, src, ant, pol)
    jones = four_correlation_jones(ctx) if four else None
    if four and jones is None:
        raise InputError(str(ctx.run.store(STORES.peel)), "correlations", "the peel solutions were made through "
                         "an E-field beam and this run's beam is not one", "rerun the peel stage (--force)")
    if cross:
        c = ctx.read(STORES.peel.cross_scale, region)[:, 0] * np.isin(mode[:, :, 0], kinds)  # (time, src)
    # four correlations: one source's model at a time (the paper's 11 sources' of a time chunk at 256 antennas are
    # 1.5 GB, their cross templates as much again); the parallel hands' models, a quarter of that, at once
    every = None if four else peel_coherencies(ctx, tel, fi, block.lst, block.pairs, [names[s] for s in used])
    for k, s in enumerate(used):
        coh = every[k] if every is not None else peel_coherencies(ctx, tel, fi, block.lst, block.pairs, [names[s]],
                                                                  jones=jones)[0]
        f = np.where(mode[:, s] == PEEL, 1.0, scale[:, s]) * np.isin(mode[:, s], kinds)  # (time, pol)
        if np.all(h[:, s] == 1):  # a subtracted or modelled source at its catalogue position: h_i conj(h_j) = 1
            term = np.broadcast_to(f[:, None], out.shape).astype(out.dtype)
        else:
            term = f[:, None] * gain_products(h[:, s], block.pairs)
        term *= coh[..., :2] if four else coh[..., None]  # in place: at 256 antennas each (time, bl,
        out += term  # pol) temporary is ~0.3 GB
        if cross:
            out_cross += cross_model(c[:, s:s + 1], gain_templates(coh[None, ..., 2:], h[None, :, s], block.pairs))
    return out, out_cross


def modelled_sources(ctx, block):
    """The fitted ``peel.model_sources`` in a block, ``sum_s a_s(t) M^s_ij`` (time, bl, freq, pol): what
    a later fit (the terrestrial templates) holds out so that the catalogued sky does not bias it; with
    the block's cross hands read, also theirs (time, bl, freq, 2), else None."""
    parts = [peel_components(ctx, block, fi, (MODEL,), cross=block.cross is not None)
             for _, fi in block.channel_indices()]
    cross = None if block.cross is None else np.stack([p[1] for p in parts], axis=2)
    return np.stack([p[0] for p in parts], axis=2), cross
