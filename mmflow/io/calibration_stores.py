"""The builders of the calibration stages' stores (gains, peel, models, diffuse, terrestrial).

Declared as :mod:`mmflow.io.run_stores` declares the others, through the handles of
:data:`mmflow.io.run_stores.STORES` (every store's and array's name is written there only); kept in a module
of their own for length. ``docs/stores.md`` lists them with the rest (:mod:`mmflow.io.store_docs`)."""
from __future__ import annotations

import numpy as np

from mmflow.io.run_stores import STORES
from mmflow.io.stores import ArraySpec, StoreSpec


def gains_store(n_interval, nf, n_ant, npol, n_time, solve_rows, apply_rows, attrs, n_src=1):
    """The calibrate stage's store (``n_src``: the calibration sources, ``attrs["sources"]``)."""
    h = STORES.gains  # its arrays' handles
    per = (1, 1, n_ant, npol)
    sol = ("interval", "freq", "antenna", "pol")
    per_pol = (("interval", "freq", "pol"), (n_interval, nf, npol), (1, 1, npol))  # dims, shape, chunks
    edges = (("interval", "edge"), (n_interval, 2), (n_interval, 2))  # each interval's first and end row
    return StoreSpec(
        STORES.gains,
        (
            ArraySpec(
                h.flux_factor,
                ("interval", "freq", "source", "pol"),
                (n_interval, nf, n_src, npol),
                (1, 1, n_src, npol),
                "float64",
                np.nan,
                doc="each calibration source's flux over its catalogue model in the interval: 1 for the "
                "unscreened ones and, on average, for those setting the scale; measured for calibrate.measure_flux; 0 "
                "where a screened source gave no model power (below the horizon)",
            ),
            ArraySpec(
                h.gains, sol, (n_interval, nf, n_ant, npol), per, "complex128", doc="complex gains, 0 where flagged"
            ),
            ArraySpec(
                h.flags, sol, (n_interval, nf, n_ant, npol), per, "bool", doc="no data, not finite, or not converged"
            ),
            ArraySpec(
                h.chi2,
                sol,
                (n_interval, nf, n_ant, npol),
                per,
                "float64",
                doc="weighted residual power per term, ``sum w |r|^2 / n`` (~1 for ``w = 1/sigma^2``)",
            ),
            ArraySpec(
                h.unexplained,
                *per_pol,
                "float64",
                np.nan,
                doc="fraction of the data's power the calibrated model leaves, ``sum w |V - G M G^H|^2 / sum w |V|^2`` "
                "(near 0 where the model explains the data; NaN: no data)",
            ),
            ArraySpec(
                h.iterations,
                *per_pol,
                "int32",
                doc="Stefcal iterations",
            ),
            ArraySpec(
                h.converged,
                *per_pol,
                "bool",
                doc="Stefcal converged",
            ),
            ArraySpec(
                h.ripple,
                ("time", "freq", "antenna", "pol"),
                (n_time, nf, n_ant, npol),
                (n_time, 1, n_ant, npol),
                "float64",
                doc="autocorrelation ripple ratio ``r(t)`` per integration (1 where not corrected)",
            ),
            ArraySpec(
                h.solve_rows,
                *edges,
                "int64",
                data=solve_rows,
                doc="the integrations each interval was solved on",
            ),
            ArraySpec(
                h.apply_rows,
                *edges,
                "int64",
                data=apply_rows,
                doc="the integrations each interval's gains correct",
            ),
        ),
        attrs,
        doc="Direction-independent calibration of the calibrate stage: gains per solution interval.",
    )


#: names of the codes of peel.zarr's ``mode`` (the values of :mod:`mmflow.calibrate.peel`'s SKIP ... MODEL)
PEEL_MODES = ("skip", "peel", "subtract", "model")


def peel_store(n_time, nf, n_src, n_ant, npol, time_chunk, attrs, cross=False):
    """The peel stage's store (``cross``: a four-correlation peel, with the cross hands' coefficients)."""
    h = STORES.peel  # its arrays' handles
    dims = ("time", "freq", "source", "pol")
    shape, ch = (n_time, nf, n_src, npol), (time_chunk, 1, n_src, npol)
    codes = ", ".join(f"{i} {name}" for i, name in enumerate(PEEL_MODES))
    cross_arrays = () if not cross else (
        ArraySpec(h.cross_scale, ("time", "freq", "source"), (n_time, nf, n_src), (time_chunk, 1, n_src),
                  "complex128", doc="complex coefficient ``c`` of each source in the cross hands: ``c h_ix conj(h_jy) "
                  "M_xy`` on xy, its conjugate on yx (a four-correlation peel; 0 skipped)"),)
    return StoreSpec(STORES.peel, (
        ArraySpec(h.dd_gains, ("time", "freq", "source", "antenna", "pol"), (n_time, nf, n_src, n_ant, npol),
                  (time_chunk, 1, n_src, n_ant, npol), "complex128",
                  doc="direction-dependent gains (a subtracted source: 1, or the phase gradient of its fitted "
                      "position)"),
        ArraySpec(h.scale, dims, shape, ch, "float64", doc="fitted flux scale (1 peeled, 0 skipped)"),
        ArraySpec(h.mode, dims, shape, ch, "int8", doc=f"mode used at the end: {codes} (:data:`PEEL_MODES`)"),
        ArraySpec(h.guard, dims, shape, ch, "bool", doc="the guard turned a peel into a subtraction"),
        ArraySpec(h.measured, dims, shape, ch, "float64",
                  doc="the guard's point-source estimate of the source in the data"),
        ArraySpec(h.removed, dims, shape, ch, "float64", doc="the guard's estimate of what peeling removed"),
        ArraySpec(h.converged, dims, shape, ch, "bool", doc="converged in the last pass"),
    ) + cross_arrays, attrs, doc=(
        "Bright sources peeled, subtracted or modelled per integration: the peel stage. Attributes: "
        "``sources``, ``peeled``, ``modelled``, ``modes`` (name -> code of ``mode``), ``fitted_models`` "
        "(the models stage's components, when it is enabled), ``pols``, ``correlations`` (xx, yy, xy, yx: a "
        "four-correlation peel through the E-field beam; absent: the parallel hands only)."))


#: columns of models.zarr's ``components``
MODEL_COLUMNS = ("x_arcmin", "y_arcmin", "flux_jy", "fwhm_major_arcmin", "fwhm_minor_arcmin", "pa_deg")
#: columns of models.zarr's ``cost``
MODEL_COSTS = ("point", "start", "fitted")


def models_store(nf, n_src, n_comp, attrs):
    """The models stage's store."""
    h = STORES.models  # its arrays' handles
    return StoreSpec(STORES.models, (
        ArraySpec(h.components, ("freq", "source", "component", "column"), (nf, n_src, n_comp, len(MODEL_COLUMNS)),
                  (1, 1, n_comp, len(MODEL_COLUMNS)), "float64",
                  doc=f"fitted Gaussian components, columns {', '.join(MODEL_COLUMNS)} (offsets east/north of "
                      "the catalogued position; fluxes renormalised to the published spectrum; flux 0 = no "
                      "component)"),
        ArraySpec(h.cost, ("freq", "source", "kind"), (nf, n_src, len(MODEL_COSTS)), (1, 1, len(MODEL_COSTS)),
                  "float64", doc=f"aperture cost of the {', '.join(MODEL_COSTS)} model"),
        ArraySpec(h.iterations, ("freq", "source"), (nf, n_src), (1, 1), "int64", doc="Nelder-Mead iterations"),
        ArraySpec(h.n_integrations, ("freq", "source"), (nf, n_src), (1, 1), "int64", doc="integrations used"),
    ), attrs, doc="Resolved source models fitted per frequency and source: the models stage.")


def diffuse_store(nf, n_samples, nbl, n_feed, sample_block):
    """The simulate stage's diffuse sky at the sampled sidereal angles
    (:mod:`mmflow.simulate.drift_modes`): what its time chunks interpolate."""
    h = STORES.diffuse  # its arrays' handles
    return StoreSpec(STORES.diffuse, (
        ArraySpec(h.samples, ("freq", "sample", "baseline", "feed"), (nf, n_samples, nbl, n_feed),
                  (1, sample_block, nbl, n_feed), "complex128",
                  doc="the diffuse sky's visibilities (Jy) at the sidereal angles ``2 pi k / N``, through each "
                  "feed's power beam (one column for a power beam)"),
    ), doc="A band-limited diffuse sky's drift scan at N sidereal angles: the simulate stage's first phase.")


def terrestrial_store(n_chunks, n_time, nf, nbl, n_comp, n_ant, npol, time_chunk, cross=False):
    """The terrestrial stage's store (``cross``: the cross hands' coefficients too, four correlations)."""
    h = STORES.terrestrial  # its arrays' handles
    cross_arrays = () if not cross else (
        ArraySpec(h.cross_amplitudes, ("time", "freq", "template"), (n_time, nf, n_comp ** 2),
                  (time_chunk, 1, n_comp ** 2), "complex128",
                  doc="complex coefficient ``a_kl(t)`` of ``u_kx u_ly^H`` in the cross hands (xy; its conjugate "
                  "on yx), in the order ``k K + l``"),
        ArraySpec(h.mean_cross_amplitudes, ("freq", "template"), (nf, n_comp ** 2), (nf, n_comp ** 2), "complex128",
                  doc="``cross_amplitudes`` averaged over the integrations fitted (subtracted where "
                  "``per_integration`` is false)"),)
    return StoreSpec(STORES.terrestrial, (
        ArraySpec(h.sum_vis, ("chunk", "freq", "baseline", "pol"), (n_chunks, nf, nbl, npol), (1, 1, nbl, npol),
                  "complex128", doc="weighted sum of the calibrated, peeled visibilities of each time chunk"),
        ArraySpec(h.sum_weight, ("chunk", "freq", "baseline", "pol"), (n_chunks, nf, nbl, npol), (1, 1, nbl, npol),
                  "float64", doc="sum of their weights"),
        ArraySpec(h.patterns, ("freq", "component", "antenna", "pol"), (nf, n_comp, n_ant, npol),
                  (nf, n_comp, n_ant, npol), "complex128",
                  doc="``u_k`` of the rank-1 templates ``B_k = u_k u_k^H`` fitted to the average"),
        ArraySpec(h.amplitudes, ("time", "freq", "template", "pol"), (n_time, nf, n_comp ** 2, npol),
                  (time_chunk, 1, n_comp ** 2, npol), "float64",
                  doc="real amplitude ``a_k(t)`` of each of the K^2 templates: ``u_k u_k^H``, then for k < l "
                  "``u_k u_l^H + u_l u_k^H`` and ``i (u_k u_l^H - u_l u_k^H)``"),
        ArraySpec(h.mean_amplitudes, ("freq", "template", "pol"), (nf, n_comp ** 2, npol), (nf, n_comp ** 2, npol),
                  "float64", doc="``amplitudes`` averaged over the integrations fitted (subtracted where "
                  "``per_integration`` is false)"),
        ArraySpec(h.sky_loss, ("freq",), (nf,), (nf,), "float64",
                  doc="the largest share of a point source's map peak, over the declinations that rise, that a "
                  "per-integration fit of the templates would take (``declination_loss``)"),
        ArraySpec(h.per_integration, ("freq",), (nf,), (nf,), "bool",
                  doc="the amplitudes subtracted per integration (true) or their means over the day "
                  "(``terrestrial.amplitudes``; ``auto``: ``sky_loss`` within the stage's limit)"),
    ) + cross_arrays, doc="Signals that do not move with the sky: the terrestrial stage.")
