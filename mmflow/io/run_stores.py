"""The stores of a run directory, each declared once (see :mod:`mmflow.io.stores`).

One builder per store (``*_store``) returns its :class:`StoreSpec`: arrays, dimensions, dtypes,
chunks, and what each store and array holds (their ``doc``). ``docs/stores.md`` is generated
from these declarations for a small reference configuration (:mod:`mmflow.io.store_docs`,
``mmflow stores show``, ``make docs``; a test keeps it in sync): read the layout there.

Gram blocks are stored per m block (``m0 <= m < m1``) padded to the block's largest size
``lmax - m0 + 1``: a few hundred arrays at lmax 1000 instead of one per m.
"""
from __future__ import annotations

import re

import numpy as np

from dataclasses import dataclass

from mmflow.conventions import m_block_slice, m_blocks, stokes_sizes
from mmflow.io.stores import ArraySpec, StoreSpec
from mmflow.mmode.normal import packed_size


class StoreName(str):
    """A store's name as the run directory holds it (``"vis.zarr"``), declared once in :data:`STORES`.

    A ``str``: paths, markers and fingerprints see the same text as before; code names a store only
    through :data:`STORES` (a test refuses ``"*.zarr"`` literals elsewhere), so a rename is one line
    here and a misspelt store fails at import, not in a task. Its arrays are its attributes
    (``STORES.gains.gains``, ``STORES.normal.gram(fi, m0)``: :data:`ARRAYS`).
    """

    __slots__ = ()

    def __getattr__(self, name):
        return _array_handle(self, name)


@dataclass(frozen=True)
class Stores:
    """The stores of a run directory, by the stage that writes them (:mod:`mmflow.workflow.pipeline`)."""

    vis: StoreName = StoreName("vis.zarr")  # simulate or ingest
    gains: StoreName = StoreName("gains.zarr")  # calibrate
    models: StoreName = StoreName("models.zarr")  # models
    peel: StoreName = StoreName("peel.zarr")  # peel
    terrestrial: StoreName = StoreName("terrestrial.zarr")  # terrestrial
    diffuse: StoreName = StoreName("diffuse.zarr")  # simulate (an interpolated diffuse sky)
    mmodes: StoreName = StoreName("mmodes.zarr")  # mmodes
    transfer: StoreName = StoreName("transfer.zarr")  # transfer (transfer.mode: store)
    partials: StoreName = StoreName("partials.zarr")  # transfer
    normal: StoreName = StoreName("normal.zarr")  # normal
    alm: StoreName = StoreName("alm.zarr")  # solve
    stokes: StoreName = StoreName("stokes.zarr")  # stokes
    clean: StoreName = StoreName("clean.zarr")  # clean

    def __iter__(self):
        return iter(vars(self).values())


#: every store's name (``STORES.vis``, ``STORES.gains``, ...)
STORES = Stores()


# ----------------------------------------------------------------------------- array handles

class ArrayName(str):
    """One array of a store as readers and writers name it (``STORES.gains.gains``): a ``str``, the
    array's path in its store (what zarr, the chunk records and fingerprints see), that knows its
    store (``.store``), so ``ctx.read(STORES.gains.gains, rows)`` needs nothing else."""

    def __new__(cls, store, name):
        self = super().__new__(cls, name)
        self.store = store
        return self

    def __reduce__(self):
        return ArrayName, (self.store, str(self))


class ArrayFamily:
    """Arrays declared once per channel (and per m block or order) from one ``template``:
    ``STORES.normal.gram(fi, m0)`` is normal.zarr's ``f{fi}/gram_b{m0:05d}``."""

    def __init__(self, store, template):
        self.store, self.template = store, template
        self.params = tuple(f.split("}")[0].split(":")[0] for f in template.split("{")[1:])  # ("fi", "m0")

    def __call__(self, *index):
        if len(index) != len(self.params):
            raise TypeError(f"{self.store}'s {self.template} takes ({', '.join(self.params)}), got {index}")
        return ArrayName(self.store, self.template.format(**dict(zip(self.params, map(int, index)))))

    def __repr__(self):
        return f"ArrayFamily({self.store!r}, {self.template!r})"

    @property
    def pattern(self):
        """The family's arrays as a glob pattern (``f*/gram_b*``)."""
        return re.sub(r"{[^}]*}", "*", self.template)

    def matches(self, path):
        """True where ``path`` is one of the family's arrays (``f1/gram_b00010`` of ``f{fi}/gram_b{m0:05d}``)."""
        return re.fullmatch(re.sub(r"\\\{[^}]*\\\}", r"[0-9]+", re.escape(self.template)), path) is not None


#: vis.zarr's arrays that stay once the visibilities have gone (:data:`RELEASED_ARRAYS`): what the stages after
#: ``mmodes`` read of it (``Stage.reads``)
VIS_METADATA = ("lst", "time_jd", "freqs_hz", "pairs", "antenna_enu", "plan_time_jd", "plan_file_rows",
                "antenna_numbers")

#: the Gram blocks' name, one array per channel and m block (normal, partials, stokes)
GRAM = "f{fi}/gram_b{m0:05d}"

#: every store's arrays, the one place their names are written: a name, or ``attribute=template`` for
#: a family (``{fi}`` the channel, ``{m0}`` the first m of an m block, ``{m}`` the order). Read as
#: ``STORES.<store>.<array>``, by readers and writers and by the store builders below, which declare
#: each array through its handle (tests/unit/io/test_run_stores.py: every handle is declared by its
#: store's builder and every declared array is a handle of that store).
ARRAYS = {
    STORES.vis: ("vis", "weights", "lst", "time_jd", "autos", "freqs_hz", "pairs", "antenna_enu", "vis_cross",
                 "weights_cross", "plan_time_jd", "plan_file_rows", "antenna_numbers"),
    STORES.mmodes: ("mmodes", "inv_var", "n_samples", "mmodes_corr", "inv_var_corr"),
    STORES.partials: (dict(gram=GRAM, rhs="f{fi}/rhs", vhv="f{fi}/vhv"),),
    STORES.normal: ("rhs", "vhv", dict(gram=GRAM)),
    STORES.alm: ("alm", "lcurve", "fraction_above", "eps_grid"),
    STORES.stokes: ("alm", "leakage", "src_residual", "src_psf_table", "src_components", "src_n_cycles",
                    "v_residual", "v_psf_table", "v_components", "v_peaks", "v_threshold", "v_noise", "v_n_cycles",
                    "v_stop", dict(gram=GRAM)),
    STORES.transfer: (dict(order="f{fi}/order", B="f{fi}/B_m{m:05d}"),),
    STORES.gains: ("flux_factor", "gains", "flags", "chi2", "unexplained", "iterations", "converged", "ripple",
                   "solve_rows", "apply_rows"),
    STORES.peel: ("dd_gains", "scale", "mode", "guard", "measured", "removed", "converged", "cross_scale"),
    STORES.models: ("components", "cost", "iterations", "n_integrations"),
    STORES.diffuse: ("samples",),
    STORES.terrestrial: ("sum_vis", "sum_weight", "patterns", "amplitudes", "cross_amplitudes", "mean_amplitudes",
                          "mean_cross_amplitudes", "sky_loss", "per_integration"),
    STORES.clean: ("psf_table", "noise", "threshold", "peaks", "components", "restored", "n_cycles", "stop",
                   dict(chol="f{fi}/chol_b{m0:05d}", psf="f{fi}/psf_b{m0:05d}",
                        residual="f{fi}/residual_b{m0:05d}")),
}


def store_handles(store, declared):
    """``{attribute: ArrayName | ArrayFamily}`` of one store; a name given twice, or one ``str`` already
    has as an attribute (``STORES.vis.count``), is refused at import."""
    names = [e for e in declared if isinstance(e, str)]
    families = {a: t for e in declared if isinstance(e, dict) for a, t in e.items()}
    out = {n: ArrayName(store, n) for n in names} | {a: ArrayFamily(store, t) for a, t in families.items()}
    bad = [a for a in out if hasattr(str, a)] + (["a name twice"] if len(out) < len(names) + len(families) else [])
    if bad:
        raise ValueError(f"{store}: array handles {bad} (rename them in mmflow.io.run_stores.ARRAYS)")
    return out


HANDLES = {str(store): store_handles(store, declared) for store, declared in ARRAYS.items()}


def array_paths(store_dir, store, attr):
    """The paths (relative to the store) of the arrays of handle ``attr`` of ``store`` that exist in the
    store's directory ``store_dir`` (one for an array, those of a family that were written)."""
    h = HANDLES[str(store)][attr]
    if isinstance(h, ArrayName):
        return [str(h)] if (store_dir / h / "zarr.json").is_file() else []
    return sorted(str(p.parent.relative_to(store_dir)) for p in store_dir.glob(f"{h.pattern}/zarr.json")
                  if h.matches(str(p.parent.relative_to(store_dir))))


def handle_of(store, path):
    """The attribute (:data:`ARRAYS`) that names array ``path`` of ``store``: ``handle_of(STORES.normal,
    "f1/gram_b00010") == "gram"``; None for an array the store does not declare."""
    for attr, h in HANDLES.get(str(store), {}).items():
        if isinstance(h, ArrayName) and h == path or isinstance(h, ArrayFamily) and h.matches(path):
            return attr
    return None


def _array_handle(store, name):
    """``STORES.<store>.<name>``: the declared array (or family), else an error naming the store's arrays."""
    if name.startswith("__") or str(store) not in HANDLES:
        raise AttributeError(name)
    try:
        return HANDLES[str(store)][name]
    except KeyError:
        raise AttributeError(f"{store} declares no array {name!r} (its arrays: "
                             f"{', '.join(HANDLES[str(store)])}; mmflow.io.run_stores.ARRAYS)") from None


# ----------------------------------------------------------------------------- the stores

#: The run's intermediates: each is released (its directory removed, the release recorded in the run
#: directory) once every enabled stage that reads it has finished, unless ``run.keep`` names it. Who
#: reads a store is what the stages declare (``Stage.inputs``: :meth:`mmflow.workflow.pipeline.Pipeline.readers`).
#: Every other store is kept: the data (``vis``), the solutions the corrections read (``gains``, ``peel``,
#: ``terrestrial``), the m-modes, the normal equations and what users open (``alm``, ``stokes``,
#: ``clean``), which a rerun with other imaging settings starts from, and the transfer blocks, which no
#: stage reads (``transfer.mode=store`` writes them for the user). Released: the partials (``normal`` holds
#: their sum), the diffuse sky's samples (``vis`` holds them interpolated) and the fitted source models
#: (``peel`` holds them in its attribute ``fitted_models``).
RELEASED_BY_DEFAULT = (STORES.partials, STORES.diffuse, STORES.models)

#: The large arrays of kept stores that later stages no longer read: each is released (its directory
#: removed, the release recorded) once every enabled stage that reads it has finished (a stage that reads
#: only some arrays of a store says which: ``Stage.reads``), unless ``run.keep`` names its store. What the
#: later stages read stays: vis.zarr's times, channels, baselines and antennas (:data:`VIS_METADATA`) after
#: the visibilities, weights and autocorrelations (read up to ``mmodes``); mmodes.zarr's ``inv_var`` and
#: ``n_samples`` after the m-modes (read by ``transfer``, ``stokes``). By attribute name (:data:`ARRAYS`).
#: normal.zarr's Grams and clean.zarr's factors stay: the products read them (the PSF at each source), so
#: releasing them would lower only the disk kept after the run, not its peak, and a rerun with other
#: imaging settings would make every stage before them again.
RELEASED_ARRAYS = {
    STORES.vis: ("vis", "weights", "autos", "vis_cross", "weights_cross"),
    STORES.mmodes: ("mmodes", "mmodes_corr"),
}

#: Released arrays (:data:`RELEASED_ARRAYS`) whose chunks go one chunk index of a dimension at a time, as the
#: tasks of their last reader that read them finish: ``{store: (dimension, axis, (array attributes))}``. The
#: last reader's task reads that chunk index alone among its tasks and says so (``Stage.task_chunks``:
#: ``{dimension: key field}``): the mmodes task ``bl_chunk = i`` reads baseline chunk ``i`` of the visibilities
#: and weights, every time and channel, so they go a baseline chunk at a time while the m-modes are made
#: (vis.zarr's ``autos``, every antenna in one chunk, goes when the stage has finished).
RELEASED_BY_CHUNK = {
    STORES.vis: ("baseline", 1, ("vis", "weights", "vis_cross", "weights_cross")),
}

#: what each dimension name of the stores below counts
DIMENSIONS = {
    "time": "integrations, in time order",
    "baseline": "antenna pairs (i, j), i <= j, autocorrelations included (``pairs``)",
    "freq": "channels (``freqs_hz``)",
    "pol": "polarisations, named by vis.zarr's attribute ``pols``",
    "cross_pol": "cross hands, named by vis.zarr's attribute ``cross_pols``",
    "file": "ingested files, in vis.zarr's attribute ``files``",
    "first_last": "first and last (inclusive) row",
    "correlation": "the four linear correlations xx, yy, xy, yx (feed p of antenna i, q of antenna j)",
    "stokes": "T, E, B, V harmonics (full Stokes: I; Q, U through healpy's E, B; V)",
    "antenna": "antennas",
    "ant": "the two antennas of a baseline",
    "enu": "east, north, up",
    "split": "data splits: 0 the full data, then ``mmode.splits`` (even / odd sidereal bins, ...)",
    "m": "azimuthal orders 0..mmax (within an array of an m block: ``m0 <= m < m1``)",
    "pm": "0: +m, 1: -m (the m-modes' and the transfer blocks' common order)",
    "l": "degrees ``m..lmax`` (block of one m) or 0..lmax",
    "triangle": "an ``n x n`` matrix's upper triangle over degrees ``(l, l')``, ``l <= l'``, packed row by row "
                "in ``n (n + 1) / 2`` elements (:func:`mmflow.mmode.normal.pack_upper`; ``n = lmax - m0 + 1``)",
    "unknown": "the unknowns of a full-Stokes block of m, ``[T (l = m..lmax); E; B; V (l = m..stokes_lmax)]``",
    "unknown2": "the second unknown index of a full-Stokes Gram matrix",
    "group": "fixed baseline groups of the transfer reduction (``transfer.groups``)",
    "eps": "trial regularisation values of the L-curve",
    "norm": "0: solution norm squared, 1: residual norm squared",
    "interval": "calibration solution intervals",
    "edge": "first and one-past-last integration",
    "source": "sources, in the order of the stage's source list",
    "component": "components of a model (Gaussian components; rank-1 terrestrial patterns)",
    "template": "terrestrial templates: the K^2 Hermitian combinations u_k u_l^H of K rank-1 patterns",
    "column": "columns of a table, named in the array's description",
    "kind": "variants of a quantity, named in the array's description",
    "chunk": "time chunks of vis.zarr",
    "alm": "healpy-layout a_lm of the m block (``m0 <= m < m1``)",
    "dec": "declinations of the PSF grid",
    "cycle": "CLEAN major cycles",
    "peak": "peaks removed per cycle",
    "quantity": "noise quantities (:data:`NOISE_FIELDS`)",
    "xyzf": "x, y, z of the unit vector (frame of date), flux in Jy",
    "xyziquv": "x, y, z of the unit vector (frame of date), then I, Q, U, V in Jy (IAU)",
    "pixel": "HEALPix pixels (RING)",
    "sample": "sidereal angles 2 pi k / N, k = 0 .. N - 1, of a band-limited sky's drift scan",
    "feed": "the feeds whose power beam a visibility is simulated through (one for a power beam)",
}


def vis_store(n_time, pairs, freqs_hz, antenna_enu, attrs, time_chunk, baseline_chunk, ingest_plan=None):
    """``attrs["pols"]`` names the polarisation axis, ``attrs["cross_pols"]`` (optional) the cross hands' axis;
    ``ingest_plan`` (ingest: ``(row_time_jd, file_rows, antenna_numbers)``, :func:`mmflow.io.ingest.plan_arrays`)
    adds what ingest's tasks read instead of rescanning the files."""
    h = STORES.vis  # its arrays' handles
    nbl, nf, n_ant, npol = len(pairs), len(freqs_hz), len(antenna_enu), len(attrs["pols"])
    ch = (time_chunk, min(baseline_chunk, nbl), 1, npol)  # one channel per chunk: a task of one channel reads it alone
    dims = ("time", "baseline", "freq", "pol")
    ncross = len(attrs.get("cross_pols") or [])
    cross = () if not ncross else (
        ArraySpec(h.vis_cross, dims[:3] + ("cross_pol",), (n_time, nbl, nf, ncross), ch[:3] + (ncross,), "complex64",
                  doc="cross-hand visibilities (xy, yx | rl, lr), Jy; where the ingested files hold them, or a "
                  "full-Stokes simulation"),
        ArraySpec(h.weights_cross, dims[:3] + ("cross_pol",), (n_time, nbl, nf, ncross), ch[:3] + (ncross,),
                  "float32", doc="their weights, 0 = flagged"))
    planned = () if ingest_plan is None else _ingest_plan_arrays(*ingest_plan)
    return StoreSpec(STORES.vis, (
        ArraySpec(h.vis, dims, (n_time, nbl, nf, npol), ch, "complex64",
                  doc="visibilities, Jy, mmflow's sign convention (docs/conventions.md)"),
        ArraySpec(h.weights, dims, (n_time, nbl, nf, npol), ch, "float32", doc="weights, 0 = flagged"),
        ArraySpec(h.lst, ("time",), (n_time,), (time_chunk,), "float64", np.nan, doc="apparent LST, radians"),
        ArraySpec(h.time_jd, ("time",), (n_time,), (time_chunk,), "float64", np.nan, doc="UTC Julian date"),
        ArraySpec(h.autos, ("time", "antenna", "freq", "pol"), (n_time, n_ant, nf, npol),
                  (time_chunk, n_ant, nf, npol), "float32", np.nan,
                  doc="autocorrelations |V_ii| (radiometer noise, ripple); NaN where absent or flagged"),
        ArraySpec(h.freqs_hz, ("freq",), (nf,), (nf,), "float64", data=freqs_hz, doc="channel frequencies, Hz"),
        ArraySpec(h.pairs, ("baseline", "ant"), (nbl, 2), (nbl, 2), "int32", data=pairs,
                  doc="antenna indices (i, j) of each baseline, i <= j"),
        ArraySpec(h.antenna_enu, ("antenna", "enu"), np.shape(antenna_enu), np.shape(antenna_enu), "float64",
                  data=antenna_enu, doc="antenna positions east, north, up of the array centre, metres"),
    ) + cross + planned, attrs, doc=(
        "Visibilities, written by the simulate or ingest stage and never rewritten: corrections are "
        "applied where the data are read. Attributes: ``pols`` names the pol axis ([I] a clean "
        "Stokes-I simulation or pseudo-Stokes files, [xx, yy] linear feeds (ee/nn alike; a corrupted or "
        "full-Stokes simulation), [rr, ll], or one hand; "
        "Stokes I is formed after the corrections, where the mmodes stage reads the data), "
        "``cross_pols`` the cross_pol axis; site (lat_deg, lon_deg, height_m), antenna_names, epoch_jd "
        "(the data's epoch: every frame rotation and header uses it), integration_s, channel_width_hz, "
        "source, files; ingest adds the attribute ingest_file_info (each file's phase state, units and "
        "polarisation recipe)."))


def _ingest_plan_arrays(row_time, file_rows, antenna_numbers):
    """Ingest's plan in vis.zarr: its tasks read these instead of rescanning the files' metadata."""
    h = STORES.vis  # its arrays' handles
    return (
        ArraySpec(h.plan_time_jd, ("time",), np.shape(row_time), np.shape(row_time), "float64", data=row_time,
                  doc="UTC Julian date of each row, from the files' metadata (ingest's plan)"),
        ArraySpec(h.plan_file_rows, ("file", "first_last"), np.shape(file_rows), np.shape(file_rows), "int64",
                  data=file_rows, doc="first and last row (inclusive) of each ingested file's integrations"),
        ArraySpec(h.antenna_numbers, ("antenna",), np.shape(antenna_numbers), np.shape(antenna_numbers), "int64",
                  data=antenna_numbers, doc="the files' antenna number of each antenna (index = antenna axis)"),
    )


def mmodes_store(n_split, nf, mmax, nbl, baseline_chunk, attrs, n_corr=0):
    """The mmodes stage's store (baseline chunks as vis.zarr's); ``n_corr`` > 0 (full Stokes) adds the
    m-modes of each correlation (xx, yy, xy, yx)."""
    h = STORES.mmodes  # its arrays' handles
    ch = min(baseline_chunk, nbl)
    pol = () if not n_corr else (
        ArraySpec(h.mmodes_corr, ("split", "freq", "m", "pm", "correlation", "baseline"),
                  (n_split, nf, mmax + 1, 2, n_corr, nbl), (n_split, nf, mmax + 1, 2, n_corr, ch), "complex128",
                  doc="m-modes of each correlation (xx, yy, xy, yx) per data split, layout of ``mmodes``; "
                      "only with imaging.stokes [I, Q, U, V]"),
        ArraySpec(h.inv_var_corr, ("freq", "correlation", "baseline"), (nf, n_corr, nbl), (nf, n_corr, ch),
                  "float64", doc="inverse noise variance of each correlation's m-modes"),
    )
    return StoreSpec(STORES.mmodes, (
        ArraySpec(h.mmodes, ("split", "freq", "m", "pm", "baseline"), (n_split, nf, mmax + 1, 2, nbl),
                  (n_split, nf, mmax + 1, 2, ch), "complex128",
                  doc="m-modes: ``[..., 0, b] = V_m``, ``[..., 1, b] = conj(V_-m)``"),
        ArraySpec(h.inv_var, ("freq", "baseline"), (nf, nbl), (nf, ch), "float64",
                  doc="inverse noise variance of each baseline's m-modes"),
        ArraySpec(h.n_samples, ("split", "freq", "baseline"), (n_split, nf, nbl), (n_split, nf, ch), "int64",
                  doc="each split's unflagged integrations (the bins' summed 0/1 weights), from which the "
                      "jackknives take each split's share ``f_k`` (:func:`mmflow.mmode.splits.split_shares`)"),
    ) + pol, attrs, doc="m-modes of the (corrected) visibilities, per data split: the mmodes stage.")


def partials_store(nf, n_groups, lmax, mmax, m_block, n_split, dtype):
    """The transfer stage's partial normal equations, one per fixed baseline group."""
    h = STORES.partials  # its arrays' handles
    arrays = []
    for fi in range(nf):
        for m0, m1 in m_blocks(mmax, m_block):
            n = lmax - m0 + 1
            arrays.append(ArraySpec(h.gram(fi, m0), ("group", "m", "triangle"), (n_groups, m1 - m0, packed_size(n)),
                                    (1, m1 - m0, packed_size(n)), dtype,
                                    doc="the group's part of ``G_m = B^H N^-1 B`` for the m of block M0, "
                                        "padded to ``lmax - m0 + 1``, its upper triangle packed"))
        arrays.append(ArraySpec(h.rhs(fi), ("group", "split", "m", "l"), (n_groups, n_split, mmax + 1, lmax + 1),
                                (1, n_split, mmax + 1, lmax + 1), dtype,
                                doc="the group's part of ``r_m = B^H N^-1 v``"))
        arrays.append(ArraySpec(h.vhv(fi), ("group", "split", "m"), (n_groups, n_split, mmax + 1),
                                (1, n_split, mmax + 1), "float64", doc="the group's part of ``v^H N^-1 v``"))
    return StoreSpec(STORES.partials, tuple(arrays), doc=(
        "Partial normal equations of the transfer stage, per frequency F: one partial sum per fixed "
        "baseline group (``transfer.groups``), in the transfer precision (complex64 for "
        "``transfer.dtype`` float32)."))


def normal_store(nf, lmax, mmax, m_block, n_split, gram_dtype="complex128"):
    """The normal stage's reduced normal equations (``gram_dtype``: the partials')."""
    h = STORES.normal  # its arrays' handles
    arrays = []
    for fi in range(nf):
        for m0, m1 in m_blocks(mmax, m_block):
            n = lmax - m0 + 1
            arrays.append(ArraySpec(h.gram(fi, m0), ("m", "triangle"), (m1 - m0, packed_size(n)),
                                    (m1 - m0, packed_size(n)), gram_dtype,
                                    doc="upper triangles of ``G_m = B^H N^-1 B`` for the m of block M0, padded "
                                        "to ``lmax - m0 + 1``, packed; the partials' precision (complex64 for float32 "
                                        "transfer: half the bytes; summed in complex128 and rounded once, so "
                                        "one group's Gram is the engine's bit for bit)"))
    arrays += [
        ArraySpec(h.rhs, ("split", "freq", "m", "l"), (n_split, nf, mmax + 1, lmax + 1),
                  (n_split, 1, m_block, lmax + 1), "complex128", doc="``r_m = B^H N^-1 v``"),
        ArraySpec(h.vhv, ("split", "freq", "m"), (n_split, nf, mmax + 1), (n_split, 1, m_block), "float64",
                  doc="``v^H N^-1 v`` (the L-curve's residual norm)"),
    ]
    return StoreSpec(STORES.normal, tuple(arrays), doc=(
        "Reduced normal equations: the normal stage sums the partials in a fixed pairwise tree "
        "(:mod:`mmflow.workflow.engine.reduce`), so the bits do not depend on the cluster."))


def alm_store(nf, lmax, mmax, m_block, n_split, eps_grid):
    """The solve stage's store."""
    h = STORES.alm  # its arrays' handles
    n_eps = len(eps_grid)
    return StoreSpec(STORES.alm, (
        ArraySpec(h.alm, ("split", "freq", "m", "l"), (n_split, nf, mmax + 1, lmax + 1),
                  (n_split, 1, m_block, lmax + 1), "complex128", doc="spherical-harmonic coefficients, Jy/sr, "
                  "frame of date"),
        ArraySpec(h.lcurve, ("freq", "m", "eps", "norm"), (nf, mmax + 1, n_eps, 2), (1, m_block, n_eps, 2),
                  "float64", doc="L-curve of the first split (zero unless ``imaging.lcurve``)"),
        ArraySpec(h.fraction_above, ("freq", "m"), (nf, mmax + 1), (1, m_block), "float64",
                  doc="fraction of singular values of ``B_m`` above ``sqrt(eps)``"),
        ArraySpec(h.eps_grid, ("eps",), (n_eps,), (n_eps,), "float64", data=eps_grid,
                  doc="the L-curve's trial eps"),
    ), doc="The solve stage's sky: a_lm per data split.")


def stokes_store(n_split, nf, lmax, mmax, clean=None, blocks=(), lmax_p=None, gram_dtype="complex128",
                 sources=None):
    """The stokes stage's full-Stokes harmonics, per data split and frequency (one chunk per m: the
    stage writes them per block of m); ``clean`` ``(n_dec, max_cycles, n_peaks)`` adds the CLEAN of V
    (``clean.enabled``), ``sources`` (the same) the full-Stokes CLEAN of the compact sources; ``blocks`` (the
    stage's ``(m0, m1)``) add each block's Grams per frequency over
    the unknowns of E, B, V to ``lmax_p`` (default ``lmax``; ``gram_dtype``: the accumulation's precision)."""
    h = STORES.stokes  # its arrays' handles
    shape, ch = (nf, 4, mmax + 1, lmax + 1), (1, 4, 1, lmax + 1)
    dims = ("freq", "stokes", "m", "l")
    arrays = []
    for fi in range(nf):
        for m0, m1 in blocks:
            n_t, n_p = stokes_sizes(m0, lmax, lmax_p)
            n = n_t + 3 * n_p
            arrays.append(ArraySpec(h.gram(fi, m0), ("m", "unknown", "unknown2"), (m1 - m0, n, n), (1, n, n),
                                    gram_dtype, doc="``G_m = B_m^H W B_m`` over ``[T; E; B; V]`` (T to "
                                    "mmode.lmax, E, B, V to imaging.stokes_lmax) of the m of block M0, each padded "
                                    "to block M0's size; what the leakage test sources and the CLEAN of V are "
                                    "imaged through (factorised again, one m at a time)"))
    arrays += [
        ArraySpec(h.alm, ("split",) + dims, (n_split,) + shape, (n_split,) + ch, "complex128",
                  doc="T, E, B, V harmonics of each data split (``mmode.splits``; Jy/sr, frame of date, healpy E/B; "
                      "IAU Q, U through :func:`mmflow.imaging.polarised.stokes_maps`), ``[split, f, X, m, l]``, "
                      "0 for l < m; the splits other than ``full`` give the jackknife noise of each Stokes map"),
        ArraySpec(h.leakage, dims, shape, ch, "complex128",
                  doc="the image through the same solve of the unpolarised sky ``[T, 0, 0, 0]`` (T the solved I of "
                      "the full data): "
                      "its E, B, V parts are the I -> Q, U, V leakage the beam model leaves"),
    ]
    if sources is not None:
        n_dec, max_cycles, n_peaks = sources
        arrays += [
            ArraySpec(h.src_residual, dims, shape, ch, "complex128",
                      doc="T, E, B, V after the full-Stokes CLEAN of the compact sources: ``alm`` minus the solve's "
                          "image of the components (:func:`mmflow.imaging.polarised_clean.clean_stokes`)"),
            ArraySpec(h.src_psf_table, ("freq", "dec", "column"), (nf, n_dec, 5), (1, n_dec, 5), "float64", np.nan,
                      doc="the I PSF by declination (the sources' restoring beam): dec, peak, major, minor, pa"),
            ArraySpec(h.src_components, ("freq", "cycle", "peak", "xyziquv"), (nf, max_cycles, n_peaks, 7),
                      (1, 1, n_peaks, 7), "float64", doc="the components: direction (frame of date) and I, Q, U, V "
                      "(IAU), Jy (all 0 = none)"),
            ArraySpec(h.src_n_cycles, ("freq",), (nf,), (1,), "int64", doc="cycles of the CLEAN of the sources"),
        ]
    if clean is not None:
        n_dec, max_cycles, n_peaks = clean
        arrays += [
            ArraySpec(h.v_residual, dims, shape, ch, "complex128",
                      doc="T, E, B, V after the CLEAN of V: ``alm`` minus the solve's image of the V components "
                          "(:func:`mmflow.imaging.polarised_clean.clean_stokes_v`) [clean.enabled]"),
            ArraySpec(h.v_psf_table, ("freq", "dec", "column"), (nf, n_dec, 5), (1, n_dec, 5), "float64", np.nan,
                      doc="the V PSF by declination: dec, peak, major, minor, pa [clean.enabled]"),
            ArraySpec(h.v_components, ("freq", "cycle", "peak", "xyzf"), (nf, max_cycles, n_peaks, 4),
                      (1, 1, n_peaks, 4), "float64", doc="V CLEAN components, frame of date, Jy (flux 0 = none) "
                      "[clean.enabled]"),
            ArraySpec(h.v_peaks, ("freq", "cycle"), (nf, max_cycles), (1, max_cycles), "float64", np.nan,
                      doc="the residual V peak each cycle started from, Jy/sr [clean.enabled]"),
            ArraySpec(h.v_threshold, ("freq",), (nf,), (1,), "float64", np.nan,
                      doc="the V CLEAN threshold, Jy/sr [clean.enabled]"),
            ArraySpec(h.v_noise, ("freq",), (nf,), (1,), "float64", np.nan,
                      doc="the V map's noise the CLEAN threshold is a multiple of: its jackknife sigma (even/odd or "
                          "per-day splits), else the dirty V map's robust rms (1.4826 MAD over the sky seen), Jy/sr "
                          "[clean.enabled]"),
            ArraySpec(h.v_n_cycles, ("freq",), (nf,), (1,), "int64", doc="V CLEAN cycles run [clean.enabled]"),
            ArraySpec(h.v_stop, ("freq",), (nf,), (1,), "int64", -1,
                      doc=f"why the V CLEAN stopped: {', '.join(f'{i} {s}' for i, s in enumerate(CLEAN_STOPS))} "
                          "[clean.enabled]"),
        ]
    return StoreSpec(STORES.stokes, tuple(arrays), {},
                     doc="full-Stokes harmonics (imaging.stokes [I, Q, U, V]), the CLEAN of the compact sources "
                         "and the CLEAN of V: the stokes stage.")


def transfer_store(nf, nbl, lmax, mmax, baseline_chunk, dtype, orders):
    """The transfer blocks, kept only with ``transfer.mode=store``."""
    h = STORES.transfer  # its arrays' handles
    arrays = []
    for fi in range(nf):
        arrays.append(ArraySpec(h.order(fi), ("baseline",), (nbl,), (nbl,), "int64", data=orders[fi],
                                doc="the rows' baselines: sorted by per-baseline lmax"))
        for m in range(mmax + 1):
            arrays.append(ArraySpec(h.B(fi, m), ("pm", "baseline", "l"), (2, nbl, lmax - m + 1),
                                    (2, min(baseline_chunk, nbl), lmax - m + 1), dtype,
                                    doc="transfer block ``B_m`` in the order ``f{F}/order`` (the -m rows 0 at m = 0)"))
    return StoreSpec(STORES.transfer, tuple(arrays), doc=(
        "Transfer matrices, per frequency F and order M: written by the transfer stage only with "
        "``transfer.mode=store``."))


# ----------------------------------------------------------------------------- clean.zarr

CLEAN_STOPS = ("threshold", "rel_threshold", "stall", "max_cycles")  # codes of clean.zarr's ``stop``
NOISE_FIELDS = ("jy_per_sr", "kelvin", "mjy_per_beam", "beam_solid_angle_sr")  # columns of clean.zarr's ``noise``


def clean_store(nf, lmax, mmax, m_block, n_dec, max_cycles, n_peaks, npix, keep_factors):
    """The CLEAN stage's store (``keep_factors``: keep the Cholesky factors)."""
    h = STORES.clean  # its arrays' handles
    arrays = []
    for fi in range(nf):
        for m0, m1 in m_blocks(mmax, m_block):
            sl = m_block_slice(lmax, m0, m1)
            n, k = lmax - m0 + 1, sl.stop - sl.start
            if keep_factors:
                arrays.append(ArraySpec(h.chol(fi, m0), ("m", "triangle"), (m1 - m0, packed_size(n)),
                                        (m1 - m0, packed_size(n)), "complex128",
                                        doc="upper Cholesky factors ``U`` of ``G_kk + eps I`` (``U^H U``), padded to "
                                        "``lmax - m0 + 1``, packed [keep_factors]; uncompressed (every cycle task "
                                        "reads its block's)", compressed=False))
            arrays.append(ArraySpec(h.psf(fi, m0), ("alm", "dec"), (k, n_dec), (k, n_dec), "complex128",
                                    doc="PSF columns of the declination grid"))
            arrays.append(ArraySpec(h.residual(fi, m0), ("cycle", "alm"), (max_cycles + 1, k), (1, k),
                                    "complex128", doc="the residual a_lm at the start of each cycle (one chunk per "
                                    "cycle, never rewritten: a killed cycle is redone from the one before)"))
    arrays += [
        ArraySpec(h.psf_table, ("freq", "kind", "dec", "column"), (nf, 2, n_dec, 5), (1, 2, n_dec, 5), "float64",
                  np.nan, doc="columns dec, peak, major, minor, pa; kind 0 the PSF, 1 the PSF CLEAN uses "
                  "(``H PSF`` for a high-pass CLEAN)"),
        ArraySpec(h.noise, ("freq", "quantity"), (nf, len(NOISE_FIELDS)), (1, len(NOISE_FIELDS)), "float64", np.nan,
                  doc=f"noise: {', '.join(NOISE_FIELDS)}"),
        ArraySpec(h.threshold, ("freq",), (nf,), (1,), "float64", np.nan, doc="CLEAN threshold, Jy/sr"),
        ArraySpec(h.peaks, ("freq", "cycle"), (nf, max_cycles), (1, 1), "float64", np.nan,
                  doc="the residual peak each cycle started from"),
        ArraySpec(h.components, ("freq", "cycle", "peak", "xyzf"), (nf, max_cycles, n_peaks, 4), (1, 1, n_peaks, 4),
                  "float64", doc="CLEAN components (flux 0 = none)"),
        ArraySpec(h.restored, ("freq", "pixel"), (nf, npix), (1, npix), "float64",
                  doc="the restored map, frame of date, Jy/sr"),
        ArraySpec(h.n_cycles, ("freq",), (nf,), (1,), "int64", doc="cycles run"),
        ArraySpec(h.stop, ("freq",), (nf,), (1,), "int64", -1,
                  doc=f"why CLEAN stopped: {', '.join(f'{i} {s}' for i, s in enumerate(CLEAN_STOPS))} "
                      "(-1: none)"),
    ]
    return StoreSpec(STORES.clean, tuple(arrays), doc=(
        "The CLEAN stage's factors, PSFs, per-cycle state and results, per frequency F and m block M0 "
        "(healpy layout within the block)."))
