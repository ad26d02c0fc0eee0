"""The products stage's cost: a task per channel holding HEALPix maps of the stage's own ``nside``
(``products.nside``, else twice :func:`mmflow.imaging.maps.default_nside`, as the stage computes it; the
CLEAN maps at ``clean.nside``, the same by default), counted as a traced task holds them at its peak
(the jackknife noise of :func:`mmflow.workflow.stages.products.clean.split_noise`, after the CLEAN
maps), and with ``products.png`` the Mollweide images it draws
(:func:`mmflow.io.export.write_mollweide_png`), whose arrays outlive each figure until Python's
garbage collector frees them (a task drawing six holds about six)."""
from __future__ import annotations

from mmflow.imaging.maps import default_nside
from mmflow.workflow.plan.work import Cost, Work

#: bytes of a map pixel (healpy synthesises float64 maps)
PIXEL_BYTES = 8.0
#: the channel's map and the FITS writer's masked copy of it
OUTPUT_MAPS = 2
#: per CLEAN map (restored, residual, model, noise; the day/night map with those splits): the map and its
#: copy in ``products.unit``
MAPS_PER_CLEAN_PRODUCT = 2
#: the jackknife's split maps (full, even, odd) and the differences it takes of them over the mask
JACKKNIFE_MAPS = 4
#: longitude samples of a Mollweide PNG (``write_mollweide_png``'s ``xsize``; latitude: half of them)
PNG_XSIZE = 1000
#: bytes per image pixel of a drawn Mollweide PNG: the projected grid's coordinates and values, the masked
#: copy and matplotlib's RGBA float and byte images (~30 MB an image traced at xsize 1000)
PNG_BYTES_PER_PIXEL = 60.0


def nside(cfg):
    """The maps' nside as the stage computes it."""
    return cfg.products.nside or 2 * default_nside(cfg.mmode.lmax)


def clean_maps(cfg):
    """CLEAN maps a task writes (0 without CLEAN)."""
    return (4 + ({"day", "night"} <= set(cfg.mmode.splits))) if cfg.clean.enabled else 0


def maps_held(cfg):
    """Maps (float64, ``nside``) a task holds at its peak."""
    return OUTPUT_MAPS + MAPS_PER_CLEAN_PRODUCT * clean_maps(cfg) + (JACKKNIFE_MAPS if cfg.clean.enabled else 0)


def png_bytes(cfg):
    """The Mollweide images a task draws (the channel's map and each CLEAN map), 0 without PNGs."""
    if not cfg.products.png:
        return 0.0
    return (1 + clean_maps(cfg)) * PNG_XSIZE * (PNG_XSIZE // 2) * PNG_BYTES_PER_PIXEL


def work(g, cfg):
    npix = 12 * nside(cfg) ** 2
    return Work(g.n_freq, npix * PIXEL_BYTES * maps_held(cfg) + png_bytes(cfg), g.npix + (g.lmax + 1) ** 2, [])


COST = Cost(work, shrink="a smaller products.nside")
