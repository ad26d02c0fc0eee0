"""Peak positions and widths of compact sources in HEALPix maps."""
from __future__ import annotations

import healpy
import numpy as np


def measure_peak(hpx_map, vec, search_radius_rad):
    """Locate the brightest peak within ``search_radius_rad`` of ``vec`` and measure it.

    The position is the brightness-weighted centroid of the connected pixels above half
    the peak; the FWHM is the diameter of a disc with the area above half maximum
    (``2 sqrt(A / pi)``), which equals the FWHM for a circular Gaussian.

    Returns
    -------
    dict with ``vec`` (unit vector), ``peak`` (map units), ``fwhm_rad`` and ``offset_rad``
    (distance from ``vec``).
    """
    nside = healpy.npix2nside(len(hpx_map))
    disc = healpy.query_disc(nside, vec, search_radius_rad)
    ipk = disc[np.argmax(hpx_map[disc])]
    peak = hpx_map[ipk]
    # grow the half-maximum region from the peak pixel
    region, frontier = {int(ipk)}, [int(ipk)]
    while frontier:
        nxt = []
        for p in frontier:
            for q in healpy.get_all_neighbours(nside, p):
                if q >= 0 and q not in region and hpx_map[q] >= 0.5 * peak:
                    region.add(int(q))
                    nxt.append(int(q))
        frontier = nxt
        if len(region) > 20000:
            break
    idx = np.fromiter(region, int)
    v = np.array(healpy.pix2vec(nside, idx)).T
    wts = hpx_map[idx] - 0.5 * peak
    c = (v * wts[:, None]).sum(0)
    c /= np.linalg.norm(c)
    area = len(idx) * healpy.nside2pixarea(nside)
    return {"vec": c, "peak": float(peak), "fwhm_rad": float(2 * np.sqrt(area / np.pi)),
            "offset_rad": float(np.arccos(np.clip(np.dot(c, vec), -1, 1)))}
