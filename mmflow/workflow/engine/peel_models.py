"""What the ``peel`` store holds, read back: the sources' models (the ``models`` stage's fitted
components, copied into ``peel.zarr``'s attributes) and the visibilities of the removed and modelled
sources. The peel stage's tasks and its ``apply`` and the ``terrestrial`` stage use it; it reads only
``models.zarr`` / ``peel.zarr`` and never the configuration.
"""
from __future__ import annotations

import numpy as np

from mmflow.calibrate.coherency import source_coherencies
from mmflow.calibrate.peel import MODEL, PEEL
from mmflow.calibrate.source_models import GaussianComponent
from mmflow.simulate.corrupt import gain_products
from mmflow.sky.sources import Source, get_sources
from mmflow.io.run_stores import STORES


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


def peel_coherencies(ctx, tel, fi, lst, pairs, names, dtype=np.complex128):
    """(n_src, time, bl) model visibilities of sources ``names`` in channel ``fi`` at the data's epoch
    (the models stage's fitted components for the sources ``peel.zarr`` lists as ``fitted_models``,
    :func:`fitted_sources`); 0 at integrations without an LST (missing). ``dtype``: the working
    precision and the result's (complex64 for the peel solve, which runs in single precision)."""
    good = np.isfinite(lst)
    out = np.zeros((len(names), len(lst), len(pairs)), dtype)
    if good.any():
        args = (tel, float(tel.freqs_hz[fi]), lst[good], fitted_sources(ctx, fi, names),
                float(ctx.vis_attrs()["epoch_jd"]), pairs, dtype)
        if good.all():
            source_coherencies(*args, out=out)  # filled in place: no copy of the sources' stack
        else:
            out[:, good] = source_coherencies(*args)
    return out


def peel_components(ctx, block, fi, kinds):
    """``sum_s f_s(t) h_si conj(h_sj) M^s_ij`` (time, bl, pol) of channel ``fi`` (of ``vis.zarr``) over the
    sources whose mode is in ``kinds``, ``f`` being 1 (peeled) or the fitted scale (subtracted,
    modelled); only the sources with such a mode somewhere in the block are computed. Reads only
    ``peel.zarr``."""
    tel = ctx.telescope()
    names = ctx.open(STORES.peel).attrs["sources"]
    region = (block.rows, slice(fi, fi + 1))
    mode = ctx.read(STORES.peel.mode, region)[:, 0]  # (time, src, pol)
    out = np.zeros(block.vis.shape[:2] + block.vis.shape[3:], complex)  # (time, bl, pol)
    used = [s for s in range(len(names)) if np.isin(mode[:, s], kinds).any()]
    if not used:
        return out
    scale = ctx.read(STORES.peel.scale, region)[:, 0]
    h = ctx.read(STORES.peel.dd_gains, region)[:, 0]  # (time, src, ant, pol)
    coh = peel_coherencies(ctx, tel, fi, block.lst, block.pairs, [names[s] for s in used])
    for k, s in enumerate(used):
        f = np.where(mode[:, s] == PEEL, 1.0, scale[:, s]) * np.isin(mode[:, s], kinds)  # (time, pol)
        if np.all(h[:, s] == 1):  # a subtracted or modelled source at its catalogue position: h_i conj(h_j) = 1
            term = np.broadcast_to(f[:, None], out.shape).astype(out.dtype)
        else:
            term = f[:, None] * gain_products(h[:, s], block.pairs)
        term *= coh[k][..., None]  # in place: at 256 antennas each (time, bl, pol) temporary is ~0.3 GB
        out += term
    return out


def modelled_sources(ctx, block):
    """The fitted ``peel.model_sources`` in a block, ``sum_s a_s(t) M^s_ij`` (time, bl, freq, pol): what
    a later fit (the terrestrial templates) holds out so that the catalogued sky does not bias it."""
    return np.stack([peel_components(ctx, block, fi, (MODEL,)) for _, fi in block.channel_indices()], axis=2)
