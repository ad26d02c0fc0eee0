"""Source models fitted from the data: Gaussian components, point positions, fluxes.

Coordinates: for a source at unit vector ``r0`` (frame of date) with tangent basis (east
``e``, north ``n``), each baseline at each time has ``(u, v, w) = (b.e, b.n, b.r0) / lambda``
(:func:`source_uvw`). Near the source, ``r ~ r0 + x e + y n`` and a point at offset (x, y)
has visibility ``S A exp(2 pi i (w + u x + v y))`` (first order in the offset, fine for
offsets << 1 rad); an elliptical Gaussian component additionally has the taper
``exp(-2 pi^2 (s_maj^2 u_maj^2 + s_min^2 u_min^2))`` with ``u_maj = u sin(pa) + v cos(pa)``,
``u_min = u cos(pa) - v sin(pa)`` (pa east of north, ``s = FWHM / sqrt(8 ln 2)``).

* :func:`fit_gaussian_components`: Nelder-Mead (scipy) on the residual variance of the
  dirty image in an aperture around the source (paper section 3.5, which used NLopt Sbplx),
  over many integrations phased to the source so that the rest of the sky smears out.
* :func:`fit_point_position`: per integration, the offset maximising the matched-filter
  response ``Re sum_b w_b V_b exp(-2 pi i (w + u x + v y))`` (coarse grid, then a quadratic
  refinement of the peak).
* :func:`fit_fluxes`: per integration, the real fluxes of K model visibility sets by
  weighted linear least squares.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from mmflow.simulate.corrupt import direction_dependent_gains
from mmflow.sky.frames import source_enu, tangent_basis
from mmflow.conventions import SPEED_OF_LIGHT
from mmflow.threads import single_threaded_blas

ARCMIN = np.pi / 180 / 60
FWHM = np.sqrt(8 * np.log(2))


def source_uvw(telescope, freq_hz, lsts, pairs, vec_date):
    """(u, v, w) in wavelengths (n_time, n_bl, 3) towards ``vec_date``, and the beam (n_time,)."""
    vec_date = np.asarray(vec_date, float)
    e, n = tangent_basis(vec_date)
    basis = np.stack([e, n, vec_date])  # (3, 3) rows e, n, r0 in the frame of date
    enu_axes = source_enu(telescope, lsts, basis)  # (3, T, 3): each axis in ENU at each time
    b = telescope.baselines_enu(pairs) * freq_hz / SPEED_OF_LIGHT  # (bl, 3)
    uvw = np.einsum("bl,ktl->tbk", b, enu_axes)
    beam = telescope.beam.power_enu(enu_axes[2], freq_hz)
    return uvw, beam


@dataclass
class GaussianComponent:
    """Offset (arcmin east, north), flux (Jy), FWHM major/minor (arcmin), position angle (deg)."""

    x_arcmin: float
    y_arcmin: float
    flux_jy: float
    fwhm_major_arcmin: float
    fwhm_minor_arcmin: float
    pa_deg: float

    def as_source_component(self, total_flux):
        """The ``mmflow.sky.sources.Source.components`` dict (fraction of ``total_flux``)."""
        return {"dra_arcmin": self.x_arcmin, "ddec_arcmin": self.y_arcmin, "fraction": self.flux_jy / total_flux,
                "fwhm_major_arcmin": self.fwhm_major_arcmin, "fwhm_minor_arcmin": self.fwhm_minor_arcmin,
                "pa_deg": self.pa_deg}


def symmetric_start(n, size_arcmin, total_flux):
    """A start for :func:`fit_gaussian_components` that knows nothing of the source but its size:
    ``n`` equal circular components of FWHM ``size / 2`` on a ring of radius ``size / 4`` at
    position angles ``0, 360 / n, ...`` (one at the centre for ``n = 1``)."""
    r = 0.0 if n == 1 else size_arcmin / 4
    pa = np.deg2rad(360.0 * np.arange(n) / n)
    return [GaussianComponent(r * np.sin(a), r * np.cos(a), total_flux / n, size_arcmin / 2, size_arcmin / 2, 0.0)
            for a in pa]


def flux_moments(components):
    """Flux-weighted centroid (2,) and second central moments (2, 2) of Gaussian components (arcmin,
    arcmin^2; axes east, north): ``mu = sum f_c x_c / F``,
    ``M = sum f_c (x_c x_c^T + R_c diag(s_maj^2, s_min^2) R_c^T) / F - mu mu^T`` with the major axis
    along ``(sin pa, cos pa)`` and ``s = FWHM / sqrt(8 ln 2)``. At baselines that barely resolve a
    source these are all its visibilities measure: ``V(u) / V(0) ~ 1 + 2 pi i u.mu - 2 pi^2 u^T (M + mu mu^T) u``."""
    f = np.array([c.flux_jy for c in components], float)
    x = np.array([[c.x_arcmin, c.y_arcmin] for c in components], float)
    mu = f @ x / f.sum()
    M = -np.outer(mu, mu)
    for fc, xc, c in zip(f, x, components):
        pa = np.deg2rad(c.pa_deg)
        R = np.array([[np.sin(pa), np.cos(pa)], [np.cos(pa), -np.sin(pa)]])  # columns: major, minor axes
        S = R @ np.diag([c.fwhm_major_arcmin**2, c.fwhm_minor_arcmin**2]) @ R.T / FWHM**2
        M += fc / f.sum() * (np.outer(xc, xc) + S)
    return mu, M


def gaussian_visibilities(uvw, beam, components):
    """Model visibilities (n_time, n_bl) of Gaussian components (see the module docstring)."""
    u, v, w = uvw[..., 0], uvw[..., 1], uvw[..., 2]
    out = np.zeros(u.shape, complex)
    for c in components:
        pa = np.deg2rad(c.pa_deg)
        umaj = u * np.sin(pa) + v * np.cos(pa)
        umin = u * np.cos(pa) - v * np.sin(pa)
        smaj = c.fwhm_major_arcmin * ARCMIN / FWHM
        smin = c.fwhm_minor_arcmin * ARCMIN / FWHM
        taper = np.exp(-2 * np.pi**2 * (smaj**2 * umaj**2 + smin**2 * umin**2))
        out += c.flux_jy * taper * np.exp(2j * np.pi * (u * c.x_arcmin * ARCMIN + v * c.y_arcmin * ARCMIN))
    return out * np.exp(2j * np.pi * w) * beam[:, None]


def aperture_pixels(radius_arcmin, step_arcmin):
    """Offsets (n_pix, 2) in radians on a square grid inside a circle."""
    k = np.arange(-radius_arcmin, radius_arcmin + 1e-9, step_arcmin)
    x, y = np.meshgrid(k, k)
    inside = x**2 + y**2 <= radius_arcmin**2
    return np.stack([x[inside], y[inside]], 1) * ARCMIN


def _unpack(p, n):
    comps = []
    for k in range(n):
        x, y, f, a, b, pa = p[6 * k: 6 * k + 6]
        comps.append(GaussianComponent(x, y, abs(f), abs(a), abs(b), pa))  # fluxes and widths >= 0
    return comps


def _canonical(c):
    """Major >= minor, position angle in (-90, 90]."""
    if c.fwhm_minor_arcmin > c.fwhm_major_arcmin:
        c.fwhm_major_arcmin, c.fwhm_minor_arcmin = c.fwhm_minor_arcmin, c.fwhm_major_arcmin
        c.pa_deg += 90.0
    c.pa_deg = 90.0 - (90.0 - c.pa_deg) % 180.0
    return c


def pack_components(components):
    """Components as one flat vector: per component ``x, y`` (arcmin), flux (Jy), FWHM major and minor
    (arcmin), position angle (deg)."""
    return np.array([[c.x_arcmin, c.y_arcmin, c.flux_jy, c.fwhm_major_arcmin, c.fwhm_minor_arcmin, c.pa_deg]
                     for c in components], float).ravel()


def fit_gaussian_components(vis, weights, uvw, beam, start, *, aperture_arcmin=None, step_arcmin=None,
                            reference_flux=None, free_amplitudes=False, maxiter=3000, xatol=1e-3, fatol=1e-9):
    """Fit Gaussian components by minimising the residual variance in an aperture.

    Parameters
    ----------
    vis, weights : ndarray (n_time, n_bl): data with everything else peeled (phasing many
        integrations smears the rest of the sky)
    uvw, beam : from :func:`source_uvw`
    start : list of GaussianComponent, the starting model
    aperture_arcmin, step_arcmin : aperture radius and pixel step (default: 2 x and 1/3 x the
        largest starting extent/FWHM)
    reference_flux : float, optional: renormalise the fitted fluxes to this total (the
        published spectrum), keeping the fitted fractions
    free_amplitudes : bool
        Scale the model of each integration ``t`` by its weighted least-squares amplitude
        ``a_t = Re sum_b w m* V / sum_b w |m|^2`` before the residual is formed (scintillation,
        beam-model errors): only the shape is then fitted, the total flux comes from
        ``reference_flux``.

    Returns
    -------
    (list of GaussianComponent, scipy OptimizeResult); the result also holds ``fun_start``,
    the cost of ``start``.
    """
    ext = max(max(np.hypot(c.x_arcmin, c.y_arcmin) + c.fwhm_major_arcmin for c in start), 1.0)
    pix = aperture_pixels(aperture_arcmin or 2 * ext, step_arcmin or ext / 3)
    w = np.asarray(weights, float)
    u, v, ww = uvw[..., 0][w > 0], uvw[..., 1][w > 0], uvw[..., 2][w > 0]
    # dirty-image operator phased to the source: I_p = Re sum_b w_b R_b exp(-2 pi i (w + u x_p + v y_p))
    E = np.exp(-2j * np.pi * (np.outer(pix[:, 0], u) + np.outer(pix[:, 1], v) + ww[None])) * w[w > 0][None]
    E /= w.sum()
    # Re(E r) = Er Re(r) - Ei Im(r): two real single-precision matrix-vector products
    Er, Ei = np.ascontiguousarray(E.real, np.float32), np.ascontiguousarray(E.imag, np.float32)
    data = vis[w > 0]
    sel_uvw = np.stack([u, v, ww], -1)[None]
    sel_beam = beam[:, None].repeat(vis.shape[1], 1)[w > 0][None]

    tidx = np.nonzero(w > 0)[0]
    wsel = w[w > 0]

    def model(p):
        comps = _unpack(p, len(start))
        m = gaussian_visibilities(sel_uvw, np.ones(1), comps)[0] * sel_beam[0]
        if free_amplitudes:
            num = np.bincount(tidx, wsel * (np.conj(m) * data).real, minlength=vis.shape[0])
            den = np.bincount(tidx, wsel * np.abs(m) ** 2, minlength=vis.shape[0])
            m = m * (num / np.where(den > 0, den, 1.0))[tidx]
        return m

    def cost(p):
        r = data - model(p)
        img = Er @ r.real.astype(np.float32) - Ei @ r.imag.astype(np.float32)
        return float(np.mean(img.astype(float) ** 2))

    # thousands of small products: one BLAS thread each is fastest (and shares the cores)
    with single_threaded_blas():
        res = minimize(cost, pack_components(start), method="Nelder-Mead",
                       options={"maxiter": maxiter, "maxfev": 2 * maxiter, "xatol": xatol, "fatol": fatol,
                                "adaptive": True})
        res["fun_start"] = cost(pack_components(start))
    comps = [_canonical(c) for c in _unpack(res.x, len(start))]
    if reference_flux is not None:
        tot = sum(c.flux_jy for c in comps)
        for c in comps:
            c.flux_jy *= reference_flux / tot
    return comps, res


def fit_point_position(vis, weights, uvw, *, radius_arcmin=30.0, step_arcmin=2.0):
    """Per integration: the offset (n_time, 2) in radians (east, north) and peak response (Jy).

    The response is ``Re sum_b w V exp(-2 pi i (w + u x + v y)) / sum_b w`` (the dirty image, a
    matched filter for a point source); the grid peak is refined by fitting a quadratic to
    its 3 x 3 neighbourhood.
    """
    k = np.arange(-radius_arcmin, radius_arcmin + 1e-9, step_arcmin) * ARCMIN
    n = len(k)
    w = np.asarray(weights, float)
    T = vis.shape[0]
    off = np.zeros((T, 2))
    peak = np.zeros(T)
    for t in range(T):
        ph = vis[t] * w[t] * np.exp(-2j * np.pi * uvw[t, :, 2])
        ex = np.exp(-2j * np.pi * np.outer(k, uvw[t, :, 0]))  # (n, bl)
        ey = np.exp(-2j * np.pi * np.outer(k, uvw[t, :, 1]))
        img = np.einsum("xb,yb,b->yx", ex, ey, ph).real / max(w[t].sum(), 1e-300)
        iy, ix = np.unravel_index(np.argmax(img), img.shape)
        iy, ix = min(max(iy, 1), n - 2), min(max(ix, 1), n - 2)
        patch = img[iy - 1: iy + 2, ix - 1: ix + 2]
        dx, dy, val = _quadratic_peak(patch)
        off[t] = [k[ix] + dx * (k[1] - k[0]), k[iy] + dy * (k[1] - k[0])]
        peak[t] = val
    return off, peak


def position_gains(telescope, freq_hz, lsts, pairs, vec_date, vis, weights, *, radius_arcmin=30.0):
    """A point source's position per integration as direction-dependent gains.

    Fits the offset ``dr`` (east, north) of the source at ``vec_date`` in ``vis`` (n_time, n_bl)
    by the matched filter of :func:`fit_point_position` and returns ``(offsets (n_time, 2) rad,
    h (n_time, n_ant))`` with ``h_i = exp(-2 pi i x_i . dr / lambda)``
    (:func:`mmflow.simulate.corrupt.direction_dependent_gains`): ``h_i conj(h_j) M_ij`` is the
    model ``M`` moved by ``dr``, so a subtracted source with a fitted position is stored and
    applied like a peeled one.
    """
    uvw, _ = source_uvw(telescope, freq_hz, lsts, pairs, vec_date)
    off, _ = fit_point_position(vis, weights, uvw, radius_arcmin=radius_arcmin)
    return off, direction_dependent_gains(telescope, freq_hz, lsts, vec_date, off[None])[0]


def _quadratic_peak(p):
    """Sub-pixel peak of a 3x3 patch (rows y, columns x) by a 2-D quadratic fit."""
    y, x = np.mgrid[-1:2, -1:2]
    A = np.stack([np.ones(9), x.ravel(), y.ravel(), x.ravel() ** 2, x.ravel() * y.ravel(), y.ravel() ** 2], 1)
    c = np.linalg.lstsq(A, p.ravel(), rcond=None)[0]
    H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    try:
        d = -np.linalg.solve(H, c[1:3])
    except np.linalg.LinAlgError:
        return 0.0, 0.0, float(p[1, 1])
    if np.any(np.abs(d) > 1):
        return 0.0, 0.0, float(p[1, 1])
    val = c[0] + c[1] * d[0] + c[2] * d[1] + c[3] * d[0] ** 2 + c[4] * d[0] * d[1] + c[5] * d[1] ** 2
    return float(d[0]), float(d[1]), float(val)


def fit_fluxes(vis, weights, models):
    """Real fluxes (n_time, K) with ``vis_t ~ sum_k s_k(t) models[k, t]`` (weighted least squares).

    ``models`` (K, n_time, n_bl) are unit-scale model visibilities (e.g. coherencies divided
    by their published flux); integrations whose normal matrix is singular get 0.
    """
    w = np.broadcast_to(np.asarray(weights, float), np.shape(vis))
    v = np.where(w > 0, vis, 0)
    G = np.einsum("tb,ktb,ltb->tkl", w, np.conj(models), models).real
    h = np.einsum("tb,ktb,tb->tk", w, np.conj(models), v).real
    ok = np.abs(np.linalg.det(G)) > 1e-300
    s = np.zeros(h.shape)
    s[ok] = np.linalg.solve(G[ok], h[ok][..., None])[..., 0]
    return s


def _hermite_functions(x, nmax):
    """Orthonormal Hermite functions ``phi_n(x) = (2^n sqrt(pi) n!)^-1/2 H_n(x) exp(-x^2/2)``, n <= nmax."""
    out = np.empty((nmax + 1,) + np.shape(x))
    out[0] = np.pi ** -0.25 * np.exp(-0.5 * np.asarray(x) ** 2)
    if nmax > 0:
        out[1] = np.sqrt(2.0) * x * out[0]
    for n in range(1, nmax):
        out[n + 1] = np.sqrt(2.0 / (n + 1)) * x * out[n] - np.sqrt(n / (n + 1)) * out[n - 1]
    return out


def shapelet_orders(nmax):
    """(n1, n2) pairs with ``n1 + n2 <= nmax``."""
    return [(a, b) for a in range(nmax + 1) for b in range(nmax + 1 - a)]


def shapelet_image(coeffs, x, y, beta, nmax):
    """Brightness ``I(x, y) = sum c_n1n2 beta^-1 phi_n1(x/beta) phi_n2(y/beta)`` (Jy/sr, offsets in rad)."""
    hx, hy = _hermite_functions(np.asarray(x) / beta, nmax), _hermite_functions(np.asarray(y) / beta, nmax)
    return sum(c * hx[a] * hy[b] for c, (a, b) in zip(coeffs, shapelet_orders(nmax))) / beta


def shapelet_visibilities(uvw, beam, beta, nmax):
    """Visibilities of each shapelet basis image: (n_coef, n_time, n_bl).

    With ``int phi_n(t) exp(i k t) dt = sqrt(2 pi) i^n phi_n(k)``, the basis image
    ``beta^-1 phi_n1(x/beta) phi_n2(y/beta)`` has visibility
    ``2 pi beta i^(n1+n2) phi_n1(2 pi u beta) phi_n2(2 pi v beta) A exp(2 pi i w)``.
    """
    hu = _hermite_functions(2 * np.pi * beta * uvw[..., 0], nmax)
    hv = _hermite_functions(2 * np.pi * beta * uvw[..., 1], nmax)
    fringe = np.exp(2j * np.pi * uvw[..., 2]) * beam[:, None] * 2 * np.pi * beta
    return np.stack([(1j ** (a + b)) * hu[a] * hv[b] * fringe for a, b in shapelet_orders(nmax)])


def fit_shapelets(vis, weights, uvw, beam, beta, nmax):
    """Real shapelet coefficients by weighted linear least squares in visibility space (the Sun).

    Returns (coeffs (n_coef,), model visibilities (n_time, n_bl)).
    """
    basis = shapelet_visibilities(uvw, beam, beta, nmax)
    w = np.sqrt(np.broadcast_to(np.asarray(weights, float), np.shape(vis))).ravel()
    A = basis.reshape(len(basis), -1).T * w[:, None]
    b = np.asarray(vis).ravel() * w
    coeffs = np.linalg.lstsq(np.concatenate([A.real, A.imag]), np.concatenate([b.real, b.imag]), rcond=None)[0]
    return coeffs, np.einsum("k,ktb->tb", coeffs, basis)
