"""The peel stage's solve of one channel's time chunk, from its visibilities and source models.

Shared by the stage (:mod:`mmflow.workflow.stages.peel.stage`, which reads the block and writes
``peel.zarr``) and ``mmflow bench calibrate`` (which times exactly this at the paper's scale):
per integration it chooses whether each source is peeled, subtracted or only modelled
(:func:`~mmflow.calibrate.peel.select_modes`, from its apparent flux and elevation), builds the
screen model's phase basis, and peels (:func:`~mmflow.calibrate.peel.peel`, in single precision
unless ``peel.tol`` asks for more: :func:`solve_dtype`);
with ``peel.fit_positions`` it fits the subtracted sources' positions and peels again.
"""
from __future__ import annotations

import numpy as np

from mmflow.calibrate.coherency import apparent_flux, source_vector_date
from mmflow.calibrate.cross_hands import fit_cross_bounded, gain_templates
from mmflow.calibrate.dd_screen import screen_basis, sky_tangents_enu
from mmflow.calibrate.peel import SKIP, SUBTRACT, peel, select_modes
from mmflow.calibrate.source_models import position_gains
from mmflow.simulate.corrupt import gain_products
from mmflow.sky.sources import get_sources
from mmflow.workflow.engine.baseline_cuts import solve_mask

#: the smallest ``peel.tol`` solved in single precision: a relative gain change (or a phase change in
#: rad) of 1e-5 is ~100 float32 roundings; below it the solve runs in double precision
SINGLE_PRECISION_TOL = 1e-5


def solve_dtype(p):
    """The working precision of the peel solve (:func:`mmflow.calibrate.peel.peel`'s ``dtype``):
    complex64, which halves the memory traffic that bounds peeling, unless ``peel.tol`` is below
    :data:`SINGLE_PRECISION_TOL` (the default 1e-4 is not)."""
    return np.complex64 if p.tol >= SINGLE_PRECISION_TOL else np.complex128


def peel_names(p):
    """Every source the peel stage fits: the removed ones (``peel.sources``), then the modelled ones."""
    return list(p.sources) + list(p.model_sources)


def peel_solve(tel, fi, lst, pairs, vis, weights, coh, p, epoch_jd, integration_s):
    """Peel one channel of a time chunk.

    Parameters
    ----------
    tel : mmflow.telescope.Telescope
    fi : int, the channel (``tel.freqs_hz[fi]``)
    lst : ndarray (time,) sidereal angles (rad; NaN: a missing integration, skipped)
    pairs : ndarray (bl, 2)
    vis, weights : ndarray (time, bl, pol): the calibrated visibilities and their weights
    coh : ndarray (n_src, time, bl), or (n_src, time, bl, pol) one per feed: the models of :func:`peel_names`
        (in :func:`solve_dtype`)
    p : the ``peel`` configuration
    epoch_jd : float, the data's epoch; integration_s : float

    Returns
    -------
    mmflow.calibrate.peel.PeelSolution, its DD gains of a subtracted source being the phase
    gradient of its fitted position (``peel.fit_positions``; 1 otherwise)
    """
    f = float(tel.freqs_hz[fi])
    good = np.isfinite(lst)
    names = peel_names(p)
    sources = get_sources(names)
    flux, elev = apparent_flux(tel, f, np.where(good, lst, 0.0), sources, epoch_jd)
    modes = select_modes(flux, elev, peelable=[n in p.peel for n in names],
                         peel_min_elevation_deg=p.peel_min_elevation_deg, peel_min_flux_jy=p.peel_min_flux_jy,
                         modelled=[n in p.model_sources for n in names])
    modes[:, ~good] = SKIP
    keep = solve_mask(tel, pairs, p.min_baseline_lambda, f)
    solint = 1 if p.solint_s is None else max(1, int(round(p.solint_s / float(integration_s))))
    basis = None
    if p.dd_model == "screen":  # the phase per unit refractive offset of each source, per integration
        vec = np.stack([source_vector_date(s, epoch_jd) for s in sources])
        basis = screen_basis(tel.layout.enu, f, sky_tangents_enu(tel, np.where(good, lst, 0.0), vec))
    kw = dict(dd_model=p.dd_model, screen_basis=basis, baseline_keep=keep, batch=p.batch, warm_start=p.warm_start,
              passes=p.passes, tol=p.tol, max_iter=p.max_iter, guard=p.guard, solint=solint, dtype=solve_dtype(p))
    out = peel(vis, weights, coh, pairs, tel.n_ant, modes, **kw)
    h = np.ones(out.dd_gains.shape[:3], complex)  # (src, time, ant): subtracted sources at their positions
    if p.fit_positions:
        h = _fit_positions(tel, f, lst, pairs, weights, out, coh, keep, good, sources, epoch_jd)
        gp = gain_products(h[..., None], pairs)  # (src, time, bl, 1)
        coh = coh * (gp if coh.ndim == 4 else gp[..., 0])
        out = peel(vis, weights, coh, pairs, tel.n_ant, modes, **kw)
    sub = out.mode == SUBTRACT  # (src, time, pol): stored DD gains are the position gradient (1: catalogue)
    out.dd_gains = np.where(sub[:, :, None, :], h[..., None], out.dd_gains)
    return out


#: ``lambda_s`` of the cross hands' fit (:func:`mmflow.calibrate.cross_hands.fit_cross`'s ``ridge``) relative to
#: the source's parallel hands, ``sum_b w (|h_ix h_jx M_xx|^2 + |h_iy h_jy M_yy|^2)``: only a source whose cross
#: hands hold less than ~1e-4 of its parallel hands' amplitude is shrunk there (what is left: < 1e-4 of its flux,
#: -40 dB); 1e-4 (shrinking below 1 %) left Cyg A at -31 to -34 dB in Q, U, V
#: (tests/acceptance/test_four_correlation_peel.py)
CROSS_RIDGE = 1e-8


def peel_cross(tel, fi, lst, pairs, cross, weights, coh, out, p):
    """The cross hands' coefficients (time, n_src) of every source the parallel hands fitted, and which of
    them the data did not measure (``|c_s|`` beyond :data:`~mmflow.calibrate.cross_hands.CROSS_MAX_RATIO` times
    the sources' common coefficient: set to it, :func:`~mmflow.calibrate.cross_hands.fit_cross_bounded`).

    ``c_s`` of :mod:`mmflow.calibrate.cross_hands` per integration, fitted jointly over the peeled, subtracted
    and modelled sources of that integration (a skipped one: 0) to the calibrated cross hands ``cross``
    (time, bl, 2: xy, yx; ``weights`` alike) against ``T^s = h_s,ip conj(h_s,jq) M^s_pq``, ``h`` the DD gains
    of ``out`` (:func:`peel_solve`'s, per feed) and ``coh`` (n_src, time, bl, 4) the sources' xx, yy, xy, yx
    through the E-field beam, with the ridge :data:`CROSS_RIDGE` x the source's parallel hands; on the
    baselines the parallel hands are solved on (``peel.min_baseline_lambda``, no autocorrelations),
    integrations with an LST; ``peel.batch`` integrations at a time (the fit's templates and design matrix
    are complex128, n_src of them per sample).
    """
    keep = solve_mask(tel, pairs, p.min_baseline_lambda, float(tel.freqs_hz[fi])) & (pairs[:, 0] != pairs[:, 1])
    w = np.asarray(weights, float) * keep[:, None] * np.isfinite(lst)[:, None, None]
    active = (out.mode[..., 0] != SKIP) & (out.mode[..., -1] != SKIP)  # (src, time)
    c = np.zeros((len(lst), len(coh)), complex)
    refused = np.zeros(c.shape, bool)
    for t0 in range(0, len(lst), p.batch):
        t = slice(t0, t0 + p.batch)
        h = out.dd_gains[:, t]
        T = gain_templates(np.asarray(coh[:, t, :, 2:], complex), h, pairs)
        par = np.abs(np.asarray(coh[:, t, :, :2]) * gain_products(h, pairs)) ** 2  # (src, time, bl, 2)
        ridge = CROSS_RIDGE * np.einsum("stbp,tbp->ts", par, w[t])
        c[t], refused[t] = fit_cross_bounded(np.where(w[t] > 0, cross[t], 0), w[t], T, active[:, t], ridge)
    return c, refused


def _fit_positions(tel, f, lst, pairs, weights, out, coh, keep, good, sources, epoch_jd):
    """DD phase gradients (src, time, ant) of each subtracted source's fitted position per
    integration (:func:`mmflow.calibrate.source_models.position_gains`) on the peeled data with the
    source put back (mean of the polarisations; autos and short baselines unused); 1 elsewhere."""
    h = np.ones(out.dd_gains.shape[:3], complex)
    w = weights.min(-1) * keep * (pairs[:, 0] != pairs[:, 1])
    for s, src in enumerate(sources):
        sub = (out.mode[s] == SUBTRACT).any(-1) & good & (w.sum(1) > 0)  # a flagged integration: no fit
        if not sub.any():
            continue
        model = coh[s][sub] if coh.ndim == 4 else coh[s][sub][..., None]  # (time, bl, pol or 1)
        data = (out.residual[sub] + out.scale[s][sub][:, None, :] * model).mean(-1)
        _, h[s, sub] = position_gains(tel, f, lst[sub], pairs, source_vector_date(src, epoch_jd), data, w[sub])
    return h
