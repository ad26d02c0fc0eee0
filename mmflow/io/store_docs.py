"""``docs/stores.md``, generated from the declared stores of :mod:`mmflow.io.run_stores`.

Every ``*_store`` builder is called once with a small reference configuration
(:func:`reference_stores`) and its :class:`~mmflow.io.stores.StoreSpec` rendered as a table:
per array its dimensions, the reference shape, the chunking rule, dtype, fill value and the
``doc`` declared beside it. A chunk size is written as the builder parameter that sets it
(:data:`CHUNK_PARAMETERS`), ``all`` where it spans the axis, else as a number. Arrays declared
once per frequency or m (``f{F}/gram_b{M0}``) are one row. ``mmflow stores show`` prints the
page; ``make docs`` writes it; a test keeps it equal to the committed file.
"""
from __future__ import annotations

import inspect
import math
import re

import numpy as np

from mmflow.io import calibration_stores as cs
from mmflow.io import run_stores as rs

#: builder parameters that set chunk sizes (their reference values are distinct from every axis length)
CHUNK_PARAMETERS = ("time_chunk", "baseline_chunk", "m_block")

#: the per-frequency / per-m parts of array names and what the page writes for them
NAME_PATTERNS = ((re.compile(r"^f\d+/"), "f{F}/"), (re.compile(r"_b\d{5}$"), "_b{M0}"),
                 (re.compile(r"_m\d{5}$"), "_m{M}"))

N_ANT, N_TIME, TIME_CHUNK, N_FREQ, LMAX, M_BLOCK = 8, 1000, 256, 2, 40, 10

REFERENCE = (f"{N_ANT} antennas ({N_ANT * (N_ANT + 1) // 2} baselines, autocorrelations included), {N_FREQ} "
             f"channels, polarisations xx, yy with cross hands xy, yx, {N_TIME} integrations, 3 data splits, "
             f"lmax = mmax = {LMAX}")


def reference_stores():
    """``[(builder, kwargs), ...]``: every store builder of :mod:`mmflow.io.run_stores` with the
    reference configuration's arguments."""
    pairs = np.array([(i, j) for i in range(N_ANT) for j in range(i, N_ANT)])
    nbl, npol, n_split, n_int = len(pairs), 2, 3, 5
    rows = np.array([[k * N_TIME // n_int, (k + 1) * N_TIME // n_int] for k in range(n_int)])
    pol_attrs = {"pols": ["xx", "yy"], "cross_pols": ["xy", "yx"]}
    blocks = dict(lmax=LMAX, mmax=LMAX, m_block=M_BLOCK, n_split=n_split)
    return [
        (rs.vis_store, dict(n_time=N_TIME, pairs=pairs, freqs_hz=np.linspace(60e6, 70e6, N_FREQ),
                            antenna_enu=np.zeros((N_ANT, 3)), attrs=pol_attrs, time_chunk=TIME_CHUNK,
                            baseline_chunk=16, ingest_plan=(np.zeros(N_TIME), np.zeros((3, 2), int),
                                                            np.arange(N_ANT)))),
        (rs.mmodes_store, dict(n_split=n_split, nf=N_FREQ, mmax=LMAX, nbl=nbl, baseline_chunk=16, attrs={},
                               n_corr=4)),
        (rs.partials_store, dict(nf=N_FREQ, n_groups=4, dtype="complex64", **blocks)),
        (rs.normal_store, dict(nf=N_FREQ, gram_dtype="complex64", **blocks)),
        (rs.alm_store, dict(nf=N_FREQ, eps_grid=np.logspace(-4, 1, 20), **blocks)),
        (rs.stokes_store, dict(n_split=n_split, nf=N_FREQ, lmax=LMAX, mmax=LMAX, clean=(8, 10, 16),
                               blocks=[(0, 8), (8, LMAX + 1)], lmax_p=LMAX // 2, gram_dtype="complex64",
                               sources=(8, 10, 16))),
        (rs.transfer_store, dict(nf=N_FREQ, nbl=nbl, lmax=LMAX, mmax=LMAX, baseline_chunk=12, dtype="complex64",
                                 orders=[np.arange(nbl)] * N_FREQ)),
        (cs.gains_store, dict(n_interval=n_int, nf=N_FREQ, n_ant=N_ANT, npol=npol, n_time=N_TIME, solve_rows=rows,
                              apply_rows=rows, attrs={}, n_src=3)),
        (cs.peel_store, dict(n_time=N_TIME, nf=N_FREQ, n_src=3, n_ant=N_ANT, npol=npol, time_chunk=TIME_CHUNK,
                             attrs={}, cross=True)),
        (cs.models_store, dict(nf=N_FREQ, n_src=3, n_comp=4, attrs={})),
        (cs.diffuse_store, dict(nf=N_FREQ, n_samples=42, nbl=nbl, n_feed=2, sample_block=8)),
        (cs.terrestrial_store, dict(n_chunks=math.ceil(N_TIME / TIME_CHUNK), n_time=N_TIME, nf=N_FREQ, nbl=nbl,
                                    n_comp=2, n_ant=N_ANT, npol=npol, time_chunk=TIME_CHUNK, cross=True)),
        (rs.clean_store, dict(nf=N_FREQ, lmax=LMAX, mmax=LMAX, m_block=M_BLOCK, n_dec=5, max_cycles=6, n_peaks=7,
                              npix=12 * 4 ** 2, keep_factors=True)),
    ]


def store_builders():
    """Every ``*_store`` function defined in :mod:`mmflow.io.run_stores` and :mod:`mmflow.io.calibration_stores`."""
    return [f for mod in (rs, cs) for name, f in vars(mod).items()
            if name.endswith("_store") and inspect.isfunction(f) and f.__module__ == mod.__name__]


def pattern(name):
    """An array's name with its frequency / m indices replaced by ``{F}``, ``{M0}``, ``{M}``."""
    for rx, repl in NAME_PATTERNS:
        name = rx.sub(repl, name)
    return name


def undocumented(specs):
    """Problems (strings): stores or arrays without ``doc``, dimensions not in ``DIMENSIONS``."""
    out = []
    for spec in specs:
        if not spec.doc.strip():
            out.append(f"{spec.path}: no doc")
        for a in spec.arrays:
            if not a.doc.strip():
                out.append(f"{spec.path}/{a.name}: no doc")
            out += [f"{spec.path}/{a.name}: dimension {d!r} not in DIMENSIONS" for d in a.dims
                    if d not in rs.DIMENSIONS]
    return out


def _chunk_rule(a, kwargs):
    names = {kwargs[p]: p for p in CHUNK_PARAMETERS if p in kwargs}
    return tuple("all" if c == n else names.get(c, str(c)) for c, n in zip(a.chunks, a.shape))


def _fill(a):
    if a.data is not None:
        return "data"
    if isinstance(a.fill_value, float) and np.isnan(a.fill_value):
        return "NaN"
    return str(np.asarray(a.fill_value).astype(a.dtype).item()).lower() if a.dtype == "bool" else str(a.fill_value)


def _text(s):
    """A declaration's doc as markdown (a table cell): Sphinx roles and literals as code, pipes escaped."""
    s = re.sub(r":(?:func|data|mod|class|attr|meth):`~?([^`]+)`", r"`\1`", " ".join(s.split()))
    return s.replace("``", "`").replace("|", r"\|")


def _tuple(xs):
    return "(" + ", ".join(map(str, xs)) + ")"


def _argument(v):
    if isinstance(v, np.ndarray):
        return f"<{' x '.join(map(str, v.shape))} array>"
    if isinstance(v, list) and v and isinstance(v[0], np.ndarray):
        return f"<{len(v)} arrays>"
    return repr(v)


def lifetime_text(writers, readers, released, arrays=None):
    """A store's lifetime as the page writes it: who writes and reads it, whether it is released, and which
    of its arrays are released alone (``arrays``: ``{array: readers}``)."""
    said = f"Written by {', '.join(writers) or 'no stage'}; read by {', '.join(readers) or 'no later stage'}. "
    if released:
        return said + ("**Released** once " + ("they have" if readers else "its writer has") + " finished (its "
                       "directory removed, the release recorded with its writer; `run.keep` keeps it).")
    if not arrays:
        return said + "Kept."
    by = {}
    for a, r in arrays.items():
        by.setdefault(r, []).append(f"`{a}`")
    alone = "; ".join(f"{', '.join(names)} once {', '.join(r) if r else 'its writer'} "
                      f"{'have' if len(r) > 1 else 'has'} finished" for r, names in by.items())
    return said + (f"Kept, but for arrays **released** alone (the later stages read the rest): {alone} (their "
                   "directories removed, the release recorded with the writer; `run.keep` keeps the store whole).")


def store_table(builder, kwargs, lifetime=None):
    """Markdown section of one store (``lifetime``: its ``(writers, readers, released, arrays)``,
    :func:`lifetime_text`)."""
    spec = builder(**kwargs)
    call = ", ".join(f"{k}={_argument(v)}" for k, v in kwargs.items())
    life = [lifetime_text(*lifetime), ""] if lifetime is not None else []
    lines = [f"## {spec.path}", "", _text(spec.doc), "", *life, f"Reference: `{builder.__name__}({call})`", "",
             "| array | dims | shape | chunks | dtype | fill | meaning |", "|---|---|---|---|---|---|---|"]
    groups = {}
    for a in spec.arrays:
        groups.setdefault(pattern(a.name), []).append(a)
    for name, arrays in groups.items():
        a = arrays[0]
        rules = {_chunk_rule(x, kwargs) for x in arrays}
        chunks = _tuple(_chunk_rule(a, kwargs)) if len(rules) == 1 else "varies"
        label = f"`{name}`" + (f" ({len(arrays)} arrays)" if len(arrays) > 1 else "")
        lines.append(f"| {label} | {_tuple(a.dims)} | {_tuple(a.shape)} | {chunks} | {a.dtype} | {_fill(a)} | "
                     f"{_text(a.doc)} |")
    return "\n".join(lines) + "\n"


def stores_markdown(lifetimes=None):
    """The whole page (``docs/stores.md``); ``lifetimes``: ``{store: (writers, readers, released)}``, the
    pipeline's (:meth:`mmflow.workflow.pipeline.Pipeline.lifetimes`: this layer does not import it)."""
    stores = reference_stores()
    problems = undocumented([b(**kw) for b, kw in stores])
    if problems:
        raise ValueError("declared stores lack descriptions: " + "; ".join(problems))
    head = [
        "# Store reference", "",
        "Generated from the declared stores (`mmflow/io/run_stores.py`: each builder's `StoreSpec` and the "
        "`doc` of every store and array) by `mmflow stores show`; regenerate with `make docs` (a test keeps "
        "it in sync). The run directory around the stores, and how chunks are completed, checked and "
        "resumed, are in [data-layout.md](data-layout.md).", "",
        "Each store names the stages that write and read it (the stages' declared inputs) and whether it "
        "is released, its directory removed, once every enabled stage that reads it has finished (the run's "
        "intermediates; `run.keep: [...]` keeps them; every other store is kept), or which of its large arrays "
        "are released alone once the stages that read them have finished (a stage that reads some arrays of a "
        "store declares which).", "",
        f"Shapes are those of a small reference configuration: {REFERENCE}; the `Reference:` line of each "
        "store gives its builder's arguments. Chunks name the builder parameter that sets them "
        f"({', '.join(f'`{p}`' for p in CHUNK_PARAMETERS)}, from the configuration), `all` for the whole "
        "axis, or a number. Fill is what an unwritten chunk would hold (`data`: written when the store is "
        "created). Names with `{F}` (frequency index), `{M0}` (first m of an m block) or `{M}` (m; both "
        "5 digits) are one array each; the shape shown is the first's.", "",
        "## Dimensions", "", "| dimension | counts |", "|---|---|",
        *(f"| {d} | {_text(text)} |" for d, text in rs.DIMENSIONS.items()), "",
    ]
    return "\n".join(head) + "\n" + "\n".join(
        store_table(b, kw, None if lifetimes is None else lifetimes[b(**kw).path]) for b, kw in stores)
