"""The products stage's cost: a task per channel holding HEALPix maps of the stage's own ``nside``
(``products.nside``, else twice :func:`mmflow.imaging.maps.default_nside`, as the stage computes it; the
CLEAN maps at ``clean.nside``, the same by default), counted as a traced task holds them at its peak
(the jackknife noise of :func:`mmflow.workflow.stages.products.clean.split_noise`, after the CLEAN
maps), and with ``products.png`` the Mollweide images it draws
(:func:`mmflow.io.export.write_mollweide_png`): the one being drawn at its full size, and what each earlier one
left until Python's garbage collector frees it.
"""
from __future__ import annotations

from mmflow.conventions import is_full_stokes
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
#: bytes per image pixel while a Mollweide PNG is drawn: the projected grid's coordinates and values, the
#: masked copy and matplotlib's RGBA float and byte images (73.8 MB traced at xsize 1000, matplotlib 3.11,
#: healpy 1.20; docs/performance.md)
PNG_DRAWING_BYTES_PER_PIXEL = 148.0
#: bytes per image pixel an earlier PNG of the same task still holds, averaged over the garbage collector's
#: passes (29 MB left by one image before a collection; 1, 3, 6 images traced 73.8, 102.7, 160.7 MB)
PNG_HELD_BYTES_PER_PIXEL = 39.0


def nside(cfg):
    """The maps' nside as the stage computes it."""
    return cfg.products.nside or 2 * default_nside(cfg.mmode.lmax)


def stokes_maps(cfg):
    """Full-Stokes maps a task holds (:func:`mmflow.workflow.stages.products.stokes.stokes_products`): I, Q,
    U, V and their leakage maps, the two polarised fractions and, with the jackknife's splits
    (``mmode.splits`` beyond ``full``), each split's four and the noise realisation's; 0 for Stokes I alone."""
    if not is_full_stokes(cfg.imaging.stokes):
        return 0
    splits = len(cfg.mmode.splits)
    return 4 + 4 + 2 + (4 * splits if splits > 1 else 0)


def images(cfg):
    """Mollweide PNGs a task draws: the channel's map, each CLEAN map, and in full Stokes the Q, U, V and
    linear-fraction views and the CLEANed V (0 without PNGs)."""
    if not cfg.products.png:
        return 0
    full = is_full_stokes(cfg.imaging.stokes)
    return 1 + clean_maps(cfg) + (4 + cfg.clean.enabled if full else 0)


def clean_maps(cfg):
    """CLEAN maps a task writes (0 without CLEAN)."""
    return (4 + ({"day", "night"} <= set(cfg.mmode.splits))) if cfg.clean.enabled else 0


def maps_held(cfg):
    """Maps (float64, ``nside``) a task holds at its peak."""
    return (OUTPUT_MAPS + MAPS_PER_CLEAN_PRODUCT * clean_maps(cfg) + (JACKKNIFE_MAPS if cfg.clean.enabled else 0)
            + stokes_maps(cfg))


def image_bytes(n):
    """The peak of drawing ``n`` Mollweide PNGs one after another: ``P (d + (n - 1) h)`` for ``P`` projected
    pixels, ``d`` the bytes per pixel of the one being drawn, ``h`` what each earlier one still holds."""
    if n <= 0:
        return 0.0
    return PNG_XSIZE * (PNG_XSIZE // 2) * (PNG_DRAWING_BYTES_PER_PIXEL + (n - 1) * PNG_HELD_BYTES_PER_PIXEL)


def png_bytes(cfg):
    """The Mollweide images' peak (:func:`image_bytes` of the task's :func:`images`)."""
    return image_bytes(images(cfg))


def work(g, cfg):
    npix = 12 * nside(cfg) ** 2
    return Work(g.n_freq, npix * PIXEL_BYTES * maps_held(cfg) + png_bytes(cfg), g.npix + (g.lmax + 1) ** 2, [])


COST = Cost(work, shrink="a smaller products.nside")
