"""The pipeline's stores and their lifetimes: who reads a store is what the stages declare."""
import ast
import re
from pathlib import Path

from mmflow.io.run_stores import RELEASED_BY_DEFAULT, STORES
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.plan.planner import live_stores
from tests.workflow_helpers import DEMO, ROOT, refused_problem

PACKAGE = Path(ROOT) / "mmflow"
NAMED = re.compile(r"\bSTORES\.(\w+)")


def _named_text(text):
    """The stores a source text names (``STORES.<attr>``)."""
    return {getattr(STORES, a) for a in NAMED.findall(text)}


def _named(path):
    """The stores a source file names (``STORES.<attr>``)."""
    return _named_text(path.read_text())


def _store_functions(path, store):
    """Top-level functions of the module at ``path`` that name ``store``, or call one that does (within it)."""
    funcs = {n.name: n for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef)}
    found = {name for name, f in funcs.items() if store in _named_text(ast.unparse(f))}
    while True:
        more = {name for name, f in funcs.items() if name not in found
                and any(isinstance(c, ast.Name) and c.id in found for c in ast.walk(f))}
        if not more:
            return found
        found |= more


def _importers(path, names):
    """The modules of the package that import any of ``names`` from the module at ``path``."""
    dotted = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    out = set()
    for p in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == dotted and {a.name for a in node.names} & names:
                out.add(p)
    return out


def test_each_stage_names_only_the_stores_it_declares():
    """A stage package that named a store it does not declare as an input or output would read a store its
    declared readers let go (the engine's helpers it calls open stores through ctx.open, which refuses
    any store the stage does not declare)."""
    for st in PIPELINE:
        named = set().union(*(_named(p) for p in (PACKAGE / "workflow" / "stages" / st.name).glob("*.py")))
        assert named <= set(st.inputs) | set(st.outputs), (st.name, named - set(st.inputs) - set(st.outputs))


def test_a_released_store_is_named_only_where_it_is_written_or_read():
    """Only its declarations (its handle, :mod:`mmflow.io.run_stores`; its builder, there or in
    :mod:`mmflow.io.calibration_stores`), its writers and its declared readers name a store that is released:
    no other module (the CLI, a report, a benchmark) can read it behind the stages' backs."""
    for store in RELEASED_BY_DEFAULT:
        writers, readers, released, _ = PIPELINE.lifetimes()[store]
        assert released
        declarations = {PACKAGE / "io" / "run_stores.py", PACKAGE / "io" / "calibration_stores.py"}
        allowed = declarations | {p for st in writers + readers
                                                       for p in (PACKAGE / "workflow" / "stages" / st).glob("*.py")}
        naming = {p for p in PACKAGE.rglob("*.py") if store in _named(p)}
        # an engine helper that names it (by its array handles) serves only its writers and readers: every
        # module importing a function of the helper that names it is one of theirs, opening it through ctx.open,
        # which refuses a store the calling stage does not declare
        helpers = {p for p in naming - allowed if p.parent == PACKAGE / "workflow" / "engine"
                   and _importers(p, _store_functions(p, store)) <= allowed}
        assert naming <= allowed | helpers and naming - declarations, \
            (store, naming - allowed - helpers)


def test_release_points_follow_the_declared_readers():
    """The partials go after normal, their one reader; the diffuse sky's samples after simulate, which
    alone reads them; the fitted models after peel; run.keep keeps what it names; a store of a disabled
    writer is not released; readers of a disabled stage do not hold a store."""
    cfg = load_config(DEMO, ["models.enabled=true", "peel.enabled=true", "peel.sources=[Cyg A, Cas A]",
                             "peel.peel=[Cyg A]", "calibrate.enabled=true"])
    assert [s.name for s in PIPELINE.readers(STORES.partials, cfg)] == ["normal"]
    assert [s.name for s in PIPELINE.readers(STORES.peel, cfg)] == ["mmodes", "products"]  # terrestrial: disabled
    assert PIPELINE.released(cfg) == {STORES.partials: "normal", STORES.diffuse: "simulate", STORES.models: "peel"}
    kept = load_config(DEMO, ["run.keep=[partials.zarr, models.zarr]"])
    assert PIPELINE.released(kept) == {STORES.diffuse: "simulate"}  # models: disabled in the demo


def test_run_keep_names_stores():
    (what, field, problem, fix), _ = refused_problem(["run.keep=[partial.zarr]"], "run.keep")
    assert "partial.zarr" in problem and "partials.zarr" in fix


def test_the_plan_counts_the_peak_of_the_live_stores():
    """Stores a (5) read by b, then b (3), then c (4): a goes after b, so c runs beside b's store alone."""
    writes = [("a", {"x": 5}), ("b", {"y": 3}), ("c", {"z": 4})]
    assert live_stores(writes, {"x": "b"}) == (8, "b", {"y": 3, "z": 4})
    assert live_stores(writes, {}) == (12, "c", {"x": 5, "y": 3, "z": 4})  # nothing released: the sum
    assert live_stores(writes, {"x": "a", "y": "b"}) == (5, "a", {"z": 4})


def test_large_arrays_go_after_the_last_stage_that_reads_them():
    """vis.zarr's visibilities, weights and autocorrelations go after mmodes, their last reader (the later
    stages read its metadata alone: ``Stage.reads``); the m-modes after transfer, their last reader (the stages
    after it read ``n_samples``), that is after normal, which runs with it channel by channel; the m-modes of
    each correlation after stokes; run.keep keeps a store's
    arrays; an ingested vis.zarr is kept whole (its files may be gone on a rerun)."""
    cfg = load_config(DEMO, ["run.keep=[]", "clean.enabled=true"])
    vis = {f"{STORES.vis}/{a}": "mmodes" for a in ("vis", "weights", "autos", "vis_cross", "weights_cross")}
    assert PIPELINE.released_arrays(cfg) == {**vis, f"{STORES.mmodes}/mmodes": "normal",  # with transfer
                                             f"{STORES.mmodes}/mmodes_corr": "mmodes"}
    assert [s.name for s in PIPELINE.array_readers(STORES.mmodes, "n_samples", cfg)] == ["clean", "products"]
    stokes = load_config(DEMO, ["run.keep=[]", "imaging.stokes=[I, Q, U, V]", "corrupt.enabled=true",
                                "beam={type: short_dipole}"])
    assert PIPELINE.released_arrays(stokes)[f"{STORES.mmodes}/mmodes_corr"] == "stokes"
    assert PIPELINE.released_arrays(stokes)[f"{STORES.mmodes}/mmodes"] == "normal"
    kept = load_config(DEMO, ["run.keep=[vis.zarr]"])
    assert set(PIPELINE.released_arrays(kept)) == {f"{STORES.mmodes}/mmodes", f"{STORES.mmodes}/mmodes_corr"}
    ingest = PIPELINE.stage("ingest")
    assert not ingest.recomputable and all(s.recomputable for s in PIPELINE if s is not ingest)


def test_the_plan_counts_a_released_array_apart_from_its_store():
    """vis.zarr (10, of which the visibilities 8) read whole by b, then only its metadata by c: the
    visibilities go after b, the rest of the store stays to the end."""
    from mmflow.workflow.plan.planner import live_stores

    writes = [("a", {"v": 2, "v/vis": 8}), ("b", {"m": 5}), ("c", {"n": 1})]
    assert live_stores(writes, {"v/vis": "b"}) == (15, "b", {"v": 2, "m": 5, "n": 1})


def test_the_plan_alternates_transfer_and_normal_by_channel():
    """Two channels of partials (5 each) summed into normal (1 each), channel by channel: channel 0's
    partials go once normal has summed them, so the peak is the m-modes (4), one channel's partials and
    the normal equations (11), not both channels' partials (16); the m-modes transfer reads (3 of the 4) go
    once both stages are complete."""
    from mmflow.workflow.plan.planner import run_live_stores

    cfg = load_config(DEMO, ["run.keep=[]"])
    writes = [("mmodes", {"mmodes.zarr": 4}, {"mmodes.zarr": {"mmodes": 3}}, {"mmodes.zarr": [2, 2]}),
              ("transfer", {"partials.zarr": 10}, {}, {"partials.zarr": [5, 5]}),
              ("normal", {"normal.zarr": 2}, {}, {"normal.zarr": [1, 1]})]
    assert run_live_stores(writes, cfg) == (4 + 5 + 2, "normal", {"mmodes.zarr": 1, "normal.zarr": 2})


def test_the_plan_releases_the_visibilities_a_baseline_chunk_at_a_time_in_mmodes():
    """vis.zarr (10: visibilities 6, weights 2) and mmodes' 4 tasks on 2 slots writing mmodes.zarr (4): each
    task's baseline chunk goes once it has finished, so the peak is the first wave's m-modes beside all of
    vis.zarr (2 + 8 + 4 * 2 / 4 = 12), not every m-mode beside it (14); the second wave's share of the
    visibilities is gone by then (10), and the rest of them with the stage."""
    from mmflow.workflow.plan.planner import run_live_stores

    cfg = load_config(DEMO, ["run.keep=[]"])
    writes = [("simulate", {"vis.zarr": 10}, {"vis.zarr": {"vis": 6, "weights": 2}}, {}),
              ("mmodes", {"mmodes.zarr": 4}, {}, {})]
    assert run_live_stores(writes, cfg) == (14, "mmodes", {"vis.zarr": 2, "mmodes.zarr": 4})
    assert run_live_stores(writes, cfg, {"mmodes": 4}, 2) == (12, "mmodes", {"vis.zarr": 2, "mmodes.zarr": 4})
    assert run_live_stores(writes, cfg, {"mmodes": 4}, 4)[0] == 14  # every task at once: nothing goes before
    kept = load_config(DEMO, ["run.keep=[vis.zarr]"])
    assert run_live_stores(writes, kept, {"mmodes": 4}, 2)[0] == 14
