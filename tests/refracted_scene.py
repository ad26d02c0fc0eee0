"""A scene of refracted, scintillating Cyg A and Cas A for the peel and calibration tests (issue 24).

A direct point-source sum (its own direction, beam and fringe code, nothing from mmflow's
simulator) for 40 real OVRO-LWA core stands within 70 m at 50 MHz: Cyg A and Cas A each moved on
the sky by a refractive offset that wanders from integration to integration (up to ~11 arcmin,
the nu^-2 scaling of 20 arcmin at 36.5 MHz) and scaled by a scintillation amplitude (log-normal,
11 % rms), plus one point source the models do not hold.
"""
import numpy as np

from mmflow.calibrate.dd_screen import screen_basis
from mmflow.telescope import ovro_lwa_layout

FREQ = 50e6
LAM = 299792458.0 / FREQ
N_TIME = 24  # integrations of 13 s (default)
# (RA, Dec) deg, flux at 50 MHz (Jy): Cyg A, Cas A (peeled) and the unmodelled source
PEELED = [(299.868, 40.734, 22000.0), (350.850, 58.815, 19000.0)]
UNMODELLED = [(330.0, 20.0, 100.0), (340.0, 35.0, 100.0), (270.0, 60.0, 100.0)]  # 27-33 deg from Cyg A
MIN_LAMBDA = 4.0


def _enu(ra_deg, dec_deg, lst_rad, lat_rad):
    """Unit ENU direction (time, 3) of (RA, Dec) at sidereal angles ``lst_rad``."""
    h = lst_rad - np.deg2rad(ra_deg)
    d = np.deg2rad(dec_deg)
    return np.stack([-np.cos(d) * np.sin(h),
                     np.sin(d) * np.cos(lat_rad) - np.cos(d) * np.cos(h) * np.sin(lat_rad),
                     np.sin(d) * np.sin(lat_rad) + np.cos(d) * np.cos(h) * np.cos(lat_rad)], -1)


def _points(x, dirs, flux):
    """``sum_p S_p A(r_p) exp(2 pi i (x_j - x_i) . r_p / lambda)`` for the upper-triangle pairs,
    ``A = sin(elevation)^1.5``: dirs (n, time, 3), flux (n, time) -> (time, n_bl)."""
    i, j = np.triu_indices(len(x))
    b = (x[j] - x[i]) / LAM
    beam = np.clip(dirs[..., 2], 0, None) ** 1.5
    return np.einsum("pt,ptb->tb", flux * beam, np.exp(2j * np.pi * np.einsum("bk,ptk->ptb", b, dirs)))


def refracted_scan(unmodelled, seed=3, n_time=None):
    """The scene (dict): ``vis`` (time, bl) = refracted Cyg A + Cas A + the unmodelled source,
    ``peeled`` their true visibilities, ``coh`` their catalogue models, ``unit`` the unmodelled
    source at 1 Jy, ``basis`` the screen basis, ``offsets`` (src, time, 2) the true refractive
    offsets (rad, along the az / alt tangents), ``scint`` (src, time) the flux factors."""
    T = n_time or N_TIME
    layout = ovro_lwa_layout("core", radius_m=70, max_antennas=40)
    x, lat = layout.enu, np.deg2rad(layout.lat_deg)
    assert x.shape[0] == 40 and np.linalg.norm(x[:, :2], axis=1).max() <= 70
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 13.0
    lst = np.deg2rad(21 * 15.0) + 2 * np.pi * t / 86164.1
    true_dirs, model_dirs, fluxes, scint, offsets = [], [], [], [], []
    for ra, dec, s in PEELED:
        r = _enu(ra, dec, lst, lat)
        # refraction: two random sinusoids per axis, periods 5-20 min, up to ~11 arcmin
        az = np.cross([0.0, 0.0, 1.0], r)
        az /= np.linalg.norm(az, axis=-1, keepdims=True)
        alt = np.cross(r, az)
        per = rng.uniform(300, 1200, (2, 2))
        ph = rng.uniform(0, 2 * np.pi, (2, 2))
        off = np.deg2rad(11 / 60) / 2 * np.sin(2 * np.pi * t[:, None, None] / per + ph).sum(-1)  # (time, 2)
        moved = r + off[:, :1] * az + off[:, 1:] * alt
        offsets.append(off)
        true_dirs.append(moved / np.linalg.norm(moved, axis=-1, keepdims=True))
        model_dirs.append(r)
        sigma = 0.2 * (36.5e6 / FREQ) ** 2
        scint.append(np.exp(sigma * rng.normal(size=T) - sigma**2 / 2))
        fluxes.append(s)
    true_dirs, model_dirs = np.stack(true_dirs), np.stack(model_dirs)
    fluxes = np.array(fluxes)[:, None]
    peeled_true = np.stack([_points(x, true_dirs[k:k + 1], fluxes[k:k + 1] * scint[k]) for k in range(2)])
    coh = np.stack([_points(x, model_dirs[k:k + 1], np.broadcast_to(fluxes[k:k + 1], (1, T))) for k in range(2)])
    ra, dec, s = unmodelled
    u_dir = _enu(ra, dec, lst, lat)[None]
    unit = _points(x, u_dir, np.ones((1, T)))  # the unmodelled source at 1 Jy
    sep = np.rad2deg(np.arccos(np.sum(u_dir[0] * model_dirs[0], -1))).mean()
    assert 20 < sep < 40 and (model_dirs[..., 2] > 0.4).all() and (u_dir[..., 2] > 0.4).all()
    # the screen's tangent vectors: the sky's east and north (about the celestial pole) at each source
    pole = np.array([0.0, np.cos(lat), np.sin(lat)])
    east = np.cross(pole, model_dirs)
    east /= np.linalg.norm(east, axis=-1, keepdims=True)
    tangents = np.stack([east, np.cross(model_dirs, east)], -2)  # (src, time, 2, 3)
    i, j = np.triu_indices(len(x))
    return dict(x=x, pairs=np.stack([i, j], 1), vis=peeled_true.sum(0) + s * unit, peeled=peeled_true, coh=coh,
                unit=unit, flux=s, basis=screen_basis(x, FREQ, tangents), offsets=np.stack(offsets),
                scint=np.stack(scint), lst=lst)


