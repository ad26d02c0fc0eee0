"""The kernels in sequence on a corrupted simulation: gains -> Stefcal -> peel Cyg A and Cas A."""
import numpy as np

from mmflow.calibrate.baselines import baseline_mask
from mmflow.calibrate.coherency import apparent_flux, source_coherencies, source_vector_date
from mmflow.calibrate.dd_screen import screen_basis, sky_tangents_enu
from mmflow.calibrate.peel import PEEL, guard_fluxes, peel, select_modes
from mmflow.calibrate.gain_apply import apply_gains
from mmflow.calibrate.stefcal import gains_per_integration, solve_gains
from mmflow.calibrate.baselines import to_matrix
from mmflow.simulate.corrupt import (antenna_gains, corrupt, dd_visibilities, direction_dependent_gains,
                                     ionospheric_offsets, scintillation)
from mmflow.simulate.visibilities import SkyPoints, simulate_drift_scan
from mmflow.sky.sources import get_sources
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.beams import SinElevationBeam

FREQ = 60e6
EPOCH = 2457700.5


def test_corrupted_cyg_cas_are_calibrated_and_peeled_below_minus_30_db():
    rng = np.random.default_rng(21)
    tel = Telescope(ovro_lwa_layout("core", max_antennas=48), SinElevationBeam(1.5), [FREQ])
    n = tel.n_ant
    pairs = tel.antenna_pairs()
    T = 16
    times = np.arange(T) * 13.0
    lsts = np.deg2rad(320.0) + 2 * np.pi * times / 86164.0
    srcs = get_sources(["Cyg A", "Cas A"])
    coh = source_coherencies(tel, FREQ, lsts, srcs, EPOCH, pairs)  # (2, T, bl)
    vec = np.stack([source_vector_date(s, EPOCH) for s in srcs])
    offs = ionospheric_offsets(2, times, FREQ, rng)
    h = direction_dependent_gains(tel, FREQ, lsts, vec, offs, scintillation(2, T, FREQ, rng))
    faint_vec = rng.normal(size=(20, 3))
    faint_vec /= np.linalg.norm(faint_vec, axis=1)[:, None]
    faint = simulate_drift_scan(tel, FREQ, lsts, SkyPoints(faint_vec, rng.uniform(5, 30, 20)), pairs)
    sky = (dd_visibilities(coh, h, pairs) + faint)[..., None].repeat(2, -1)
    g, _ = antenna_gains(n, 2, times, rng)
    vis, truth = corrupt(sky, pairs, rng, gains=g, noise={"bandwidth_hz": 24e3, "integration_s": 13.0})
    w = np.ones(vis.shape)
    keep = baseline_mask(pairs, tel.layout.enu, FREQ, 4.0)

    # direction-independent gains against the nominal Cyg A + Cas A model, one solution
    sol = solve_gains(vis, coh.sum(0)[..., None], w, pairs, n, baseline_keep=keep)
    assert sol.converged.all() and not sol.flags.any()
    gt, _ = gains_per_integration(sol, T)
    ratio = gt / g  # per antenna: a common complex factor per pol, up to scintillation/refraction
    ratio /= ratio[:, sol.ref_ant[0, 0]][:, None]
    assert np.abs(np.abs(ratio) - 1).max() < 0.1
    cal, wc = apply_gains(vis, w, pairs, gt)

    # peel both per integration (refractive offset + amplitude, the default), starting from no offset
    flux, elev = apparent_flux(tel, FREQ, lsts, srcs, EPOCH)
    modes = select_modes(flux, elev, peelable=[True, True])
    assert (modes == PEEL).all()
    basis = screen_basis(tel.layout.enu, FREQ, sky_tangents_enu(tel, lsts, vec))
    out = peel(cal, wc, coh, pairs, n, modes, screen_basis=basis, baseline_keep=keep, passes=4, tol=1e-6, max_iter=200)
    assert not out.guard.any()
    # what is left at each source position, against the source's apparent flux
    clean = cal - out.residual  # what peeling removed
    for s in range(2):
        for p in range(2):
            R = to_matrix(out.residual[..., p] - faint, pairs, n)  # the faint sky is not modelled
            M = to_matrix(coh[s], pairs, n)
            W = to_matrix(np.where(keep, 1.0, 0.0)[None].repeat(T, 0), pairs, n)
            left, _ = guard_fluxes(R, M, W, np.ones((T, n)))
            left /= W.sum(axis=(1, 2))
            suppression_db = 10 * np.log10(np.abs(left).max() / flux[s].min())
            print(f"source {s} pol {p}: {suppression_db:.1f} dB")
            assert suppression_db < -30, (s, p, suppression_db)
    assert np.isfinite(clean).all()


def test_ripple_correction_then_one_track_solution_calibrates_two_hours():
    """Autos carry the HVAC sawtooth; the ripple ratio removes it, one Stefcal track solves the
    rest, and the corrected cross-correlations follow the sky to 0.3 % for two hours. Without
    the ripple step the sawtooth (2.3 % peak to peak in power) stays in the data."""
    from mmflow.calibrate.ripple import apply_ripple, autocorrelations, ripple_ratio
    from mmflow.calibrate.stefcal import best_track

    rng = np.random.default_rng(8)
    tel = Telescope(ovro_lwa_layout("core", max_antennas=16), SinElevationBeam(1.5), [FREQ])
    n = tel.n_ant
    pairs = tel.antenna_pairs()
    T = 554  # two hours of 13 s
    times = np.arange(T) * 13.0
    lsts = np.deg2rad(300.0) + 2 * np.pi * times / 86164.0
    srcs = get_sources(["Cyg A", "Cas A"])
    coh = source_coherencies(tel, FREQ, lsts, srcs, EPOCH, pairs)
    sky = coh.sum(0)
    sky[:, pairs[:, 0] == pairs[:, 1]] += 3e4  # the diffuse sky dominates the autocorrelations
    sky = sky[..., None].repeat(2, -1)
    g, power = antenna_gains(n, 2, times, rng, drift=False)
    vis, _ = corrupt(sky, pairs, rng, gains=g)
    w = np.ones(vis.shape)
    autos, wa = autocorrelations(vis, w, pairs, n)
    ratio, out = ripple_ratio(autos, wa, 13.0)
    assert not out.any()
    flat, w1 = apply_ripple(vis, w, pairs, ratio)
    flux, _ = apparent_flux(tel, FREQ, lsts, srcs, EPOCH)
    track = best_track(flux, 100)
    cross = pairs[:, 0] != pairs[:, 1]
    model = coh.sum(0)[..., None]
    sol = solve_gains(flat[track], model[track], w1[track], pairs, n)
    cal, _ = apply_gains(flat, w1, pairs, sol.gains[0])
    resid = np.abs(cal[:, cross] / sky[:, cross] - 1)
    # the track's gains hold for two hours to the ripple correction's accuracy
    ref = np.abs(cal[:, cross] / sky[:, cross])
    assert np.percentile(resid, 99) < 0.01, np.percentile(resid, 99)
    assert np.std(ref / ref.mean(0), axis=0).max() < 0.003
    # the same without the ripple step: the sawtooth is left in the data
    sol0 = solve_gains(vis[track], model[track], w[track], pairs, n)
    raw, _ = apply_gains(vis, w, pairs, sol0.gains[0])
    ref0 = np.abs(raw[:, cross] / sky[:, cross])
    assert np.std(ref0 / ref0.mean(0), axis=0).max() > 0.005
