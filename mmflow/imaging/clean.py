"""m-mode CLEAN (paper section 2.4) as kernels a stage can fan out over m blocks.

One major cycle:

1. synthesise the residual map from the residual alm (HEALPix, frame of date);
2. pick up to ``n_peaks`` peaks, at least ``min_sep`` apart (so the sidelobes of one batch do
   not interact), in the observed sky (declination ``dec = pi/2 - theta`` above ``dec_min``),
   each refined to sub-pixel position by a quadratic fit to its 3x3 neighbourhood;
3. components ``c_i = gain r_i / P(dec_i)``, with ``r_i`` the residual at the peak and
   ``P(dec)`` the PSF's value at its own source (Jy/sr per Jy, from :func:`psf.psf_table`);
4. ``x = sum_i c_i conj(Y_lm(r_i))`` (:func:`mmflow.sky.harmonics.point_sources_alm`), then per
   m block ``residual_m -= observe(x_m)`` with ``observe = (G_kk + eps I)^-1 G`` and the
   m-filters (:func:`psf.observe_block`): this is :func:`observe_and_subtract`, the kernel
   mapped over m blocks;
5. record the components; stop on a threshold (peak < k sigma), a stall, a relative
   threshold, or a cycle limit (:func:`stop_reason`).

Finally the components are restored with an elliptical Gaussian per declination fitted to the
PSF's main lobe (:func:`restore_map`), flux-conserving: a component of c Jy adds a Gaussian of
integral c Jy (Jy/sr map units), onto the residual map.

The state between cycles (:class:`CleanState`) is plain arrays, checkpointable as npz or zarr.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import healpy
import numpy as np

from mmflow.conventions import m_block_slice, m_blocks, n_alm
from mmflow.imaging import psf as psf_mod
from mmflow.imaging.maps import default_nside
from mmflow.imaging.solvers import solve_alm
from mmflow.sky.harmonics import point_sources_alm


# ----------------------------------------------------------------------------- sky masks

def dec_of_pixels(nside, pix=None):
    """Declination of HEALPix (RING) pixels: ``dec = pi/2 - theta`` (not ``acos z``)."""
    pix = np.arange(healpy.nside2npix(nside)) if pix is None else pix
    theta, _ = healpy.pix2ang(nside, pix)
    return np.pi / 2 - theta


def never_seen_dec_min(lat_rad, min_elevation_rad=0.0):
    """Lowest declination that rises ``min_elevation`` above the horizon: ``lat - pi/2 + el``."""
    return lat_rad - np.pi / 2 + min_elevation_rad


def observed_mask(nside, dec_min_rad, dec_max_rad=np.pi / 2):
    """Pixels with ``dec_min <= dec <= dec_max`` (the sky the array sees)."""
    dec = dec_of_pixels(nside)
    return (dec >= dec_min_rad) & (dec <= dec_max_rad)


# ----------------------------------------------------------------------------- peaks

def find_peaks(hmap, n_peaks, min_sep_rad, mask=None, absolute=True, floor=-np.inf):
    """Up to ``n_peaks`` pixels of largest value, pairwise at least ``min_sep_rad`` apart.

    Greedy in decreasing value over local maxima (pixels not below any of their 8
    neighbours): a pixel is taken unless it lies within ``min_sep`` of one already taken.
    ``absolute``: rank by ``|map|`` (negative components allowed); pixels scoring below
    ``floor`` are never taken (an exact plateau counts as a local maximum: set a floor).

    Returns
    -------
    ndarray of pixel indices (RING), in decreasing rank.
    """
    nside = healpy.npix2nside(len(hmap))
    score = np.abs(hmap) if absolute else np.asarray(hmap, float)
    ok = score >= floor
    cand = np.flatnonzero(ok if mask is None else ok & mask)
    excluded = np.zeros(len(hmap), bool)
    taken, done = [], 0
    n_top = min(len(cand), max(64 * n_peaks, 4096))
    while True:
        # candidates ranked by score: the best n_top first (a prefix of the full ranking)
        if len(cand) == 0:
            break
        part = np.argpartition(-score[cand], n_top - 1)[:n_top] if n_top < len(cand) else np.arange(len(cand))
        ranked = cand[part[np.argsort(-score[cand[part]], kind="stable")]]
        ranked = ranked[_local_maxima(score, ranked, nside)]
        for p in ranked[done:]:
            done += 1
            if excluded[p]:
                continue
            taken.append(p)
            excluded[healpy.query_disc(nside, healpy.pix2vec(nside, p), min_sep_rad, inclusive=True)] = True
            if len(taken) == n_peaks:
                return np.asarray(taken, int)
        if n_top >= len(cand):
            break
        n_top = len(cand)
    return np.asarray(taken, int)


def _local_maxima(score, pix, nside):
    """Which of ``pix`` are not below any of their (up to 8) neighbours."""
    nb = healpy.get_all_neighbours(nside, pix).reshape(8, -1)
    nbv = np.where(nb >= 0, score[np.maximum(nb, 0)], -np.inf)
    return np.all(score[pix][None] >= nbv, axis=0)


def refine_peaks(hmap, pix):
    """Sub-pixel peak positions and values from a quadratic fit to each pixel's neighbourhood.

    ``g = c0 + c1 x + c2 y + c3 x^2 + c4 xy + c5 y^2`` over the pixel and its 8 neighbours in
    tangent-plane coordinates, with ``g = ln |f|`` when the 9 values share the peak's sign
    (exact for a Gaussian lobe) and ``g = |f|`` otherwise; the vertex is used when the fit
    is a maximum of ``g`` within one pixel of the centre, else the pixel centre itself.

    Returns
    -------
    vecs : ndarray (n, 3), values : ndarray (n,)
    """
    nside = healpy.npix2nside(len(hmap))
    pix = np.asarray(pix, int)
    vecs = np.array(healpy.pix2vec(nside, pix)).T.reshape(-1, 3)
    vals = np.asarray(hmap, float)[pix].copy()
    if len(pix) == 0:
        return vecs, vals
    nb = healpy.get_all_neighbours(nside, pix).reshape(8, -1)
    res = healpy.nside2resol(nside)
    for i, p in enumerate(pix):
        q = np.concatenate([[p], nb[:, i][nb[:, i] >= 0]])
        x, y = psf_mod.to_tangent(np.array(healpy.pix2vec(nside, q)).T, vecs[i])
        f = hmap[q] * np.sign(vals[i] or 1.0)
        log = bool(np.all(f > 0))  # a Gaussian-like lobe: fit ln f (exact for a Gaussian)
        a = np.stack([np.ones_like(x), x / res, y / res, (x / res) ** 2, x * y / res**2, (y / res) ** 2], 1)
        c = np.linalg.lstsq(a, np.log(f) if log else f, rcond=None)[0]
        hess = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
        if np.linalg.eigvalsh(hess).max() >= 0:
            continue
        x0, y0 = np.linalg.solve(hess, -c[1:3])
        if np.hypot(x0, y0) > 1.0:
            continue
        top = c[0] + 0.5 * (c[1] * x0 + c[2] * y0)
        vecs[i] = psf_mod.from_tangent(x0 * res, y0 * res, vecs[i])
        vals[i] = np.sign(vals[i] or 1.0) * (np.exp(top) if log else top)
    return vecs, vals


# ----------------------------------------------------------------------------- components

def component_fluxes(vecs, values, table, gain):
    """``c_i = gain r_i / P(dec_i)`` with ``P`` interpolated from the PSF table's ``peak``."""
    dec = np.arcsin(np.clip(vecs[:, 2], -1, 1))
    return gain * values / psf_mod.interp_table(table, dec, "peak")


def observe_and_subtract(residual_block, component_block, ops, lmax, m_start, m_stop, weights=None):
    """The per-m-block kernel: ``residual_m - observe_m(x_m)`` for ``m_start <= m < m_stop``.

    ``residual_block`` and ``component_block`` are the :func:`mmflow.conventions.m_block_slice`
    of the residual alm and of the components' alm; ``ops`` maps m to :class:`psf.BlockOperator`
    (m without an operator are left unchanged: no data constrain them). ``weights`` (over
    l = 0..lmax): subtract ``w_l observe(x)`` instead (a high-pass CLEAN). Returns a new array.
    """
    return np.asarray(residual_block, np.complex128) - psf_mod.observe_range(ops, component_block, lmax, m_start,
                                                                             m_stop, weights)


# ----------------------------------------------------------------------------- state

@dataclass
class CleanState:
    """Everything needed to resume CLEAN after a kill, as plain arrays.

    Attributes
    ----------
    residual_alm : complex ndarray (n_alm,), Jy/sr
    comp_vec : ndarray (n, 3) component directions (frame of date)
    comp_flux : ndarray (n,) Jy
    comp_cycle : ndarray (n,) int, the major cycle each component came from
    peaks : ndarray (cycle,) residual peak (Jy/sr) seen at the start of each cycle
    cycle : int, major cycles done
    """

    residual_alm: np.ndarray
    comp_vec: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    comp_flux: np.ndarray = field(default_factory=lambda: np.zeros(0))
    comp_cycle: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    peaks: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cycle: int = 0

    def to_arrays(self):
        return {"residual_alm": self.residual_alm, "comp_vec": self.comp_vec, "comp_flux": self.comp_flux,
                "comp_cycle": self.comp_cycle, "peaks": self.peaks, "cycle": np.array(self.cycle)}

    @classmethod
    def from_arrays(cls, arrays):
        a = {k: np.asarray(v) for k, v in dict(arrays).items()}
        return cls(a["residual_alm"].astype(np.complex128), a["comp_vec"].reshape(-1, 3), a["comp_flux"],
                   a["comp_cycle"].astype(int), a["peaks"], int(a["cycle"]))

    def advance(self, residual_alm, vecs, fluxes, peak):
        """The state after one more cycle with these components and the peak it started from."""
        return CleanState(residual_alm, np.concatenate([self.comp_vec, np.reshape(vecs, (-1, 3))]),
                          np.concatenate([self.comp_flux, fluxes]),
                          np.concatenate([self.comp_cycle, np.full(len(fluxes), self.cycle, int)]),
                          np.append(self.peaks, peak), self.cycle + 1)

    def model_alm(self, lmax):
        """``sum_i c_i conj(Y_lm(r_i))`` of every component so far."""
        return point_sources_alm(self.comp_vec, self.comp_flux, lmax) if len(self.comp_flux) else \
            np.zeros(n_alm(lmax), np.complex128)


def stop_reason(peaks, threshold=0.0, rel_threshold=0.0, max_cycles=None, stall_cycles=10, stall_frac=0.01):
    """Why CLEAN should stop after the peaks seen so far (None: go on).

    ``threshold``: the last peak is below ``threshold`` (e.g. ``k sigma_jackknife``);
    ``rel_threshold``: below that fraction of the first peak; ``stall``: the best peak of the
    last ``stall_cycles`` cycles is not ``stall_frac`` below the best one before them;
    ``max_cycles``: that many cycles are done.
    """
    peaks = np.asarray(peaks, float)
    if len(peaks) == 0:
        return None
    if peaks[-1] <= threshold:
        return "threshold"
    if rel_threshold > 0 and peaks[-1] <= rel_threshold * peaks[0]:
        return "rel_threshold"
    if max_cycles is not None and len(peaks) >= max_cycles:
        return "max_cycles"
    if stall_cycles and len(peaks) > stall_cycles:
        before, recent = peaks[:-stall_cycles].min(), peaks[-stall_cycles:].min()
        if recent > (1 - stall_frac) * before:
            return "stall"
    return None


# ----------------------------------------------------------------------------- driver

def select_components(residual_map, table, mask, n_peaks=256, min_sep_rad=np.deg2rad(3.0), gain=0.15,
                      threshold=0.0, absolute=True, peak_frac=0.0):
    """Peaks of one cycle and their components: ``(vecs, fluxes, peak)``.

    ``peak`` is the largest (absolute) residual in the mask before this cycle's subtraction;
    peaks below ``threshold`` or below ``peak_frac * peak`` (a sidelobe of the brightest, in
    the manner of Clark's minor-cycle limit) give no component.
    """
    score = np.abs(residual_map) if absolute else residual_map
    inside = score if mask is None else score[mask]
    peak = float(inside.max()) if len(inside) else 0.0
    pix = find_peaks(residual_map, n_peaks, min_sep_rad, mask, absolute,
                     floor=np.nextafter(max(threshold, peak_frac * peak), np.inf))
    vecs, vals = refine_peaks(residual_map, pix)
    keep = (np.abs(vals) if absolute else vals) > threshold
    return vecs[keep], component_fluxes(vecs[keep], vals[keep], table, gain), peak


@dataclass
class CleanOptions:
    """CLEAN's knobs (paper defaults: 256 peaks, 3 deg apart, loop gain 0.15, 3 sigma).

    ``absolute``: rank peaks by ``|residual|`` (negative components allowed); ``peak_frac``:
    no component from a peak below that fraction of the cycle's largest; ``rel_threshold``,
    ``max_cycles``, ``stall_cycles``, ``stall_frac``: see :func:`stop_reason`.
    """

    n_peaks: int = 256
    min_sep_deg: float = 3.0
    gain: float = 0.15
    k_sigma: float = 3.0
    absolute: bool = True
    peak_frac: float = 0.1
    max_cycles: int = 1000
    rel_threshold: float = 0.0
    stall_cycles: int = 10
    stall_frac: float = 0.1

    def stop(self, peaks, threshold):
        return stop_reason(peaks, threshold, self.rel_threshold, self.max_cycles, self.stall_cycles,
                           self.stall_frac)


def plan_cycle(residual_alm, lmax, table, mask, nside, opts=None, threshold=0.0):
    """The driver's part of a major cycle: synthesis, peaks and the components.

    Returns ``(vecs, fluxes, peak, seconds)`` with ``seconds`` of ``synthesis`` and ``peaks``;
    the components' alm (:func:`component_alm`) are then observed and subtracted per m block.
    """
    opts = opts or CleanOptions()
    t = {}
    t0 = time.perf_counter()
    rmap = healpy.alm2map(residual_alm, nside, lmax=lmax)
    t["synthesis"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vecs, flux, peak = select_components(rmap, table, mask, opts.n_peaks, np.deg2rad(opts.min_sep_deg), opts.gain,
                                         threshold, opts.absolute, opts.peak_frac)
    t["peaks"] = time.perf_counter() - t0
    return vecs, flux, peak, t


def component_alm(vecs, fluxes, lmax, m_stop=None, m_start=0):
    """``x = sum_i c_i conj(Y_lm(r_i))`` for ``m_start <= m < m_stop`` (default all m): healpy layout
    up to ``m_stop``, or its :func:`mmflow.conventions.m_block_slice` ``(m_start, m_stop)`` part."""
    mmax = lmax if m_stop is None else min(lmax, m_stop - 1)
    if len(fluxes) == 0:
        sl = m_block_slice(lmax, m_start, mmax + 1)
        return np.zeros(sl.stop - sl.start, np.complex128)
    return point_sources_alm(vecs, fluxes, lmax, mmax, m_start)


def major_cycle(state, ops, lmax, table, mask, nside, opts=None, threshold=0.0, m_block=None, weights=None):
    """One major cycle in memory (synthesis, peaks, component alm, observe and subtract).

    ``m_block``: m per call of :func:`observe_and_subtract` (None: one call), as a stage
    would fan them out; ``weights``: high-pass CLEAN (the state's residual is ``H r``, the
    table that of ``H`` PSF). Returns the updated state and the seconds spent in ``synthesis``,
    ``peaks``, ``components`` (the component alm) and ``observe``.
    """
    vecs, flux, peak, t = plan_cycle(state.residual_alm, lmax, table, mask, nside, opts, threshold)
    t0 = time.perf_counter()
    x = component_alm(vecs, flux, lmax)
    t["components"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    resid = state.residual_alm.copy()
    for m0, m1 in m_blocks(lmax, m_block or lmax + 1):
        sl = m_block_slice(lmax, m0, m1)
        resid[sl] = observe_and_subtract(resid[sl], x[sl], ops, lmax, m0, m1, weights)
    t["observe"] = time.perf_counter() - t0
    return state.advance(resid, vecs, flux, peak), t


def clean_alm(dirty_alm, ops, lmax, table, dec_min_rad, noise=None, opts=None, nside=None, state=None,
              checkpoint=None, weights=None):
    """CLEAN a dirty alm in memory with the per-block kernels; returns ``(state, reason)``.

    Parameters
    ----------
    dirty_alm : complex ndarray (n_alm,), Jy/sr, frame of date, the filtered Tikhonov solution
    ops : dict m -> :class:`psf.BlockOperator` (the same eps and filters as the dirty map)
    table : dict from :func:`psf.psf_table` (``dec`` and ``peak`` are used)
    dec_min_rad : float, the lowest declination the array sees (:func:`never_seen_dec_min`)
    noise : float, optional, the map noise (Jy/sr); the threshold is ``opts.k_sigma * noise``
    opts : :class:`CleanOptions`
    nside : int, the residual map's resolution (default twice :func:`maps.default_nside`)
    state : :class:`CleanState`, optional, to resume; ``checkpoint(state)`` is called each cycle.
    weights : ndarray (lmax + 1,), optional, high-pass CLEAN (:func:`psf.highpass_weights`):
        CLEAN ``H dirty`` with ``H observe`` and a table of ``H PSF``; combine the result
        with :func:`restore_highpass`.
    """
    opts = opts or CleanOptions()
    nside = nside or 2 * default_nside(lmax)
    mask = observed_mask(nside, dec_min_rad)
    threshold = 0.0 if noise is None else opts.k_sigma * noise
    start = dirty_alm if weights is None else psf_mod.apply_l_weights(dirty_alm, lmax, weights)
    state = state or CleanState(np.array(start, np.complex128, copy=True))
    reason = opts.stop(state.peaks, threshold)
    while reason is None:
        state, _ = major_cycle(state, ops, lmax, table, mask, nside, opts, threshold, weights=weights)
        if checkpoint is not None:
            checkpoint(state)
        reason = opts.stop(state.peaks, threshold)
    return state, reason


# ----------------------------------------------------------------------------- restoring

def merge_components(vecs, fluxes, nside):
    """Sum components falling in one pixel of ``nside`` (``|flux|``-weighted mean direction); components of
    zero flux add nothing and are left out (a pixel of only such would have no direction: the full-Stokes
    CLEAN's sources fitted in I alone have Q = U = V = 0)."""
    vecs, fluxes = np.asarray(vecs, float).reshape(-1, 3), np.asarray(fluxes, float).reshape(-1)
    vecs, fluxes = vecs[fluxes != 0], fluxes[fluxes != 0]
    if len(fluxes) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    pix = healpy.vec2pix(nside, *vecs.T)
    uniq, inv = np.unique(pix, return_inverse=True)
    flux = np.bincount(inv, fluxes, len(uniq))
    vsum = np.stack([np.bincount(inv, vecs[:, j] * np.abs(fluxes), len(uniq)) for j in range(3)], 1)
    vsum /= np.linalg.norm(vsum, axis=1)[:, None]
    return vsum, flux


def north_rotation(vecs, matrix):
    """Angle ``psi`` (rad) by which position angles change from frame A to ``v_B = matrix v_A``.

    A direction at position angle ``p`` (north through east) at ``r`` in A has position angle
    ``p + psi`` at ``matrix r`` in B: ``psi = atan2(R n_A . e_B, R n_A . n_B)``, with ``(e, n)``
    the east and north unit vectors (:func:`psf.tangent_frame`).
    """
    rmat = np.asarray(matrix, float)
    out = np.zeros(len(vecs))
    for i, v in enumerate(np.asarray(vecs, float).reshape(-1, 3)):
        _, _, n_a = psf_mod.tangent_frame(v)
        _, e_b, n_b = psf_mod.tangent_frame(rmat @ v)
        rn = rmat @ n_a
        out[i] = np.arctan2(rn @ e_b, rn @ n_b)
    return out


def restore_map(residual_map, comp_vec, comp_flux, table, radius_fwhm=2.5, to_frame=None):
    """Residual map plus each component convolved with the elliptical Gaussian of its declination.

    A component of ``c`` Jy at ``r_i`` adds ``c / (2 pi s_a s_b) exp(-(x_a^2/s_a^2 + x_b^2/s_b^2)/2)``
    (Jy/sr; integral ``c``), ``x_a, x_b`` azimuthal-equidistant offsets along the major and minor
    axes, ``s = FWHM / sqrt(8 ln 2)``, beam ``(major, minor, pa)`` interpolated from ``table``
    at the component's declination of date.

    ``to_frame``: matrix ``v_out = R v_date`` when ``residual_map`` is in another frame (ICRS,
    Galactic): the components are moved there and their beams' position angles turned by
    :func:`north_rotation` (widths do not change), so nothing is resampled.
    """
    out = np.array(residual_map, float, copy=True)
    nside = healpy.npix2nside(len(out))
    vecs, flux = merge_components(np.asarray(comp_vec, float).reshape(-1, 3), np.asarray(comp_flux, float),
                                  4 * nside)
    dec = np.arcsin(np.clip(vecs[:, 2], -1, 1))
    maj, mnr, pa = (psf_mod.interp_table(table, dec, key) for key in ("major", "minor", "pa"))
    if to_frame is not None:
        pa = pa + north_rotation(vecs, to_frame)
        vecs = vecs @ np.asarray(to_frame, float).T
    sa, sb = maj / psf_mod.FWHM_PER_SIGMA, mnr / psf_mod.FWHM_PER_SIGMA
    bad = ~(np.isfinite(vecs).all(axis=1) & np.isfinite(flux) & (maj > 0) & (mnr > 0))
    if bad.any():  # healpy aborts the whole process on a non-finite direction or a radius <= 0
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"restore_map: {int(bad.sum())} of {len(flux)} components have no finite direction, flux "
                         f"or beam (the first: {vecs[i]}, {flux[i]} Jy, beam {maj[i]:.3g} x {mnr[i]:.3g} rad)")
    for i in range(len(flux)):
        disc = healpy.query_disc(nside, vecs[i], radius_fwhm * maj[i], inclusive=True)
        x, y = psf_mod.to_tangent(np.array(healpy.pix2vec(nside, disc)).T, vecs[i])
        xa = x * np.sin(pa[i]) + y * np.cos(pa[i])
        xb = x * np.cos(pa[i]) - y * np.sin(pa[i])
        out[disc] += flux[i] / (2 * np.pi * sa[i] * sb[i]) * np.exp(-0.5 * ((xa / sa[i]) ** 2 + (xb / sb[i]) ** 2))
    return out


def model_map(comp_vec, comp_flux, nside, to_frame=None):
    """The components as a map: each pixel holds the flux of the components in it over the
    pixel's solid angle (Jy/sr; the map's integral is the total flux)."""
    vecs = np.asarray(comp_vec, float).reshape(-1, 3)
    if to_frame is not None:
        vecs = vecs @ np.asarray(to_frame, float).T
    out = np.zeros(healpy.nside2npix(nside))
    if len(vecs):
        np.add.at(out, healpy.vec2pix(nside, *vecs.T), np.asarray(comp_flux, float))
    return out / healpy.nside2pixarea(nside)


def clean_normal_equations(acc, eps, lat_rad, filters=None, noise=None, opts=None, dec_step_deg=1.0, nside=None):
    """The engine path: dirty map, PSF table and CLEAN from one frequency's normal equations.

    ``acc``: :class:`~mmflow.mmode.normal.NormalAccumulator` (Grams and right-hand sides);
    ``eps`` and ``filters`` as for :func:`mmflow.imaging.solvers.solve_alm`. The PSF table runs
    from the lowest declination seen to the pole in ``dec_step_deg`` steps.

    Returns
    -------
    dict: ``dirty_alm``, ``state`` (:class:`CleanState`), ``reason``, ``table``, ``nside``,
    ``residual_map`` and ``restored_map`` (Jy/sr, frame of date).
    """
    lmax = acc.lmax
    dirty = solve_alm(acc, eps, filters=filters)
    ops = psf_mod.block_operators(acc, eps, filters)
    dec_min = never_seen_dec_min(lat_rad)
    table = psf_mod.psf_table(ops, lmax, np.deg2rad(np.arange(np.rad2deg(dec_min), 90.0 + 1e-9, dec_step_deg)))
    nside = nside or 2 * default_nside(lmax)
    state, reason = clean_alm(dirty, ops, lmax, table, dec_min, noise, opts, nside)
    resid = healpy.alm2map(state.residual_alm, nside, lmax=lmax)
    return {"dirty_alm": dirty, "state": state, "reason": reason, "table": table, "nside": nside,
            "residual_map": resid, "restored_map": restore_map(resid, state.comp_vec, state.comp_flux, table)}


def restore_highpass(dirty_alm, state, table, weights, lmax, nside):
    """Restored map of a high-pass CLEAN: ``(1 - H) dirty + H residual-and-restored-components``.

    The smooth part never went through CLEAN; the Gaussian-restored components are high-passed
    (``map2alm``, ``w_l``, ``alm2map``) so their large scales are not counted twice.
    """
    comps = restore_map(np.zeros(healpy.nside2npix(nside)), state.comp_vec, state.comp_flux, table)
    return combine_highpass(dirty_alm, state.residual_alm, comps, weights, lmax)


def combine_highpass(dirty_alm, residual_alm, components_map, weights, lmax):
    """``(1 - H) dirty + H residual + H components`` as a map at the components map's nside.

    ``H = diag(w_l)`` commutes with rotations, so the alm and the restored-components map may
    be in any one frame (the workflow uses the output frame).
    """
    nside = healpy.npix2nside(len(components_map))
    smooth = psf_mod.apply_l_weights(dirty_alm, lmax, 1.0 - np.asarray(weights))
    comps_alm = psf_mod.apply_l_weights(healpy.map2alm(components_map, lmax=lmax, iter=3), lmax, weights)
    return healpy.alm2map(smooth + residual_alm + comps_alm, nside, lmax=lmax)
