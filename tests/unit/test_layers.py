"""One-way layers (issue 23): the package's import graph, deferred imports included.

The layers, lowest first (docs/architecture.md):

0. ``base``: ``mmflow/__init__.py``, ``conventions``, ``errors``, ``offline``, ``compiled_cache``, ``threads``,
   ``allocator``, ``machine``, ``import_thread`` -- numbers, exceptions and process settings every layer shares;
   numpy only.
1. ``kernels``: ``telescope``, ``sky``, ``mmode``, ``imaging``, ``calibrate``, ``simulate``,
   ``analysis`` -- numpy/scipy, no dask, no configuration, no files of a run.
2. ``io``: reading and writing data, stores, reports.
3. ``workflow``: configuration, stages, dask graph, runner.
4. ``bench``: benchmarks that time kernels and whole workflows.
5. ``cli``: the ``mmflow`` command.

A module may import only from its own layer or one below. The graph is read with :mod:`ast`
(every ``import`` statement anywhere in a module, function bodies included, relative imports
resolved), never by importing the package, so deferred imports cannot hide a cycle.
"""
from __future__ import annotations

import ast
from collections import defaultdict
from functools import lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2] / "mmflow"

LAYERS = {"base": 0, "kernels": 1, "io": 2, "workflow": 3, "bench": 4, "cli": 5}
BASE_MODULES = {
    "mmflow",
    "mmflow.conventions",
    "mmflow.errors",
    "mmflow.paths",
    "mmflow.environ",
    "mmflow.offline",
    "mmflow.threads",
    "mmflow.import_thread",
    "mmflow.allocator",
    "mmflow.machine",
    "mmflow.compiled_cache",
}
KERNEL_PACKAGES = ("telescope", "sky", "mmode", "imaging", "calibrate", "simulate", "analysis")

# --- the graph -------------------------------------------------------------------------------

def module_files(root):
    """``{module name: path}`` of every ``.py`` file under the package directory ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


@lru_cache(maxsize=None)
def parsed(path):
    """The module at ``path`` as an :mod:`ast` tree (parsed once for every check of this file)."""
    return ast.parse(path.read_text(), filename=str(path))


def _resolve(node, module, is_package):
    """Absolute module named by an ``ImportFrom``'s ``module`` part (relative levels resolved)."""
    if node.level == 0:
        return node.module
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_edges(root):
    """Every import of a module of the package by another, deferred imports included.

    Returns
    -------
    modules : dict
        ``{name: path}``.
    edges : list of (importer, imported, line, names)
        ``names`` are the names taken by ``from ... import``; ``from pkg import sub`` where
        ``pkg.sub`` is a module is an edge to ``pkg.sub``.
    """
    modules = module_files(root)
    top = root.name
    edges = []
    for name, path in modules.items():
        tree = parsed(path)
        is_package = path.name == "__init__.py"
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    target = alias.name
                    while target and target not in modules:
                        target = target.rpartition(".")[0]
                    if target and target.split(".")[0] == top:
                        edges.append((name, target, node.lineno, ()))
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(node, name, is_package)
                if not base or base.split(".")[0] != top:
                    continue
                plain = []
                for alias in node.names:
                    if f"{base}.{alias.name}" in modules:
                        edges.append((name, f"{base}.{alias.name}", node.lineno, ()))
                    else:
                        plain.append(alias.name)
                if plain:
                    target = base
                    while target and target not in modules:
                        target = target.rpartition(".")[0]
                    edges.append((name, target, node.lineno, tuple(plain)))
    return modules, [e for e in edges if e[0] != e[1] or e[3]]


def cycles(nodes, edges):
    """Strongly connected components with more than one node (Tarjan), each sorted."""
    succ = defaultdict(set)
    for a, b in edges:
        if a != b:
            succ[a].add(b)
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = [0]

    def visit(v):  # recursion depth = longest import chain, a few dozen at most
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(succ[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return sorted(out)


def layer_of(module):
    """``(layer name, area)``: the area is the kernel package, or the layer's name."""
    parts = module.split(".")
    if module in BASE_MODULES:
        return "base", "base"
    if len(parts) > 1 and parts[1] in KERNEL_PACKAGES:
        return "kernels", parts[1]
    if len(parts) > 1 and parts[1] in ("io", "workflow", "bench", "cli"):
        return parts[1], parts[1]
    raise AssertionError(f"{module}: no layer assigned; add it to tests/unit/test_layers.py and "
                         "docs/architecture.md")


def upward(edges):
    """Edges from a lower layer to a higher one, as ``'a -> b (line n)'`` strings."""
    out = []
    for a, b, line, _ in edges:
        if LAYERS[layer_of(b)[0]] > LAYERS[layer_of(a)[0]]:
            out.append(f"{a} -> {b} (line {line})")
    return out


def private_imports(edges):
    """``from m import _x`` across modules (dunder names excepted)."""
    return [f"{a} imports {', '.join(n for n in names if n.startswith('_') and not n.startswith('__'))} "
            f"from {b} (line {line})"
            for a, b, line, names in edges
            if any(n.startswith("_") and not n.startswith("__") for n in names)]


def stage_of(module):
    """The stage package a module belongs to (``'peel'`` for ``mmflow.workflow.stages.peel.solve``), else None."""
    parts = module.split(".")
    if parts[1:3] == ["workflow", "stages"] and len(parts) >= 4 and parts[3] != "base":
        return parts[3]
    return None


MODULES, EDGES = import_edges(ROOT)


def _edges_in(region):
    """Edges whose importer lies in ``region``: a layer name, or ``kernels:<package>``."""
    def inside(m):
        layer, area = layer_of(m)
        return area == region.split(":")[1] if region.startswith("kernels:") else layer == region
    return [e for e in EDGES if inside(e[0])]


def _describe(comps, edges):
    lines = []
    for comp in comps:
        members = set(comp)
        inner = sorted({f"  {a} -> {b} (line {line})" for a, b, line, _ in edges
                        if a in members and b in members})
        lines.append(f"cycle of {len(comp)} modules:\n" + "\n".join(inner))
    return "\n".join(lines)


# --- the cases -------------------------------------------------------------------------------

REGIONS = ["base", *(f"kernels:{p}" for p in KERNEL_PACKAGES), "io", "workflow", "bench", "cli"]


def test_every_module_has_a_layer():
    for m in MODULES:
        layer_of(m)


@pytest.mark.parametrize("region", REGIONS)
def test_no_import_cycle(region):
    """No cycle among the modules a region's modules import."""
    comps = [c for c in cycles(MODULES, [(a, b) for a, b, _, _ in EDGES])
             if any(e[0] in c for e in _edges_in(region))]
    assert not comps, "\n" + _describe(comps, EDGES)


def test_no_cycle_between_kernel_packages():
    """The kernel packages depend one way (e.g. imaging on mmode, simulate on calibrate)."""
    pkg_edges = {(layer_of(a)[1], layer_of(b)[1]) for a, b, _, _ in EDGES
                 if layer_of(a)[0] == layer_of(b)[0] == "kernels"}
    comps = cycles(set(KERNEL_PACKAGES), pkg_edges)
    detail = [f"  {a} -> {b} (line {line})" for a, b, line, _ in EDGES
              if any(layer_of(a)[1] in c and layer_of(b)[1] in c and layer_of(a)[1] != layer_of(b)[1]
                     and layer_of(a)[0] == layer_of(b)[0] == "kernels" for c in comps)]
    assert not comps, f"package cycles {comps}:\n" + "\n".join(sorted(detail))


@pytest.mark.parametrize("region", REGIONS)
def test_no_upward_import(region):
    bad = upward(_edges_in(region))
    assert not bad, "\n" + "\n".join(bad)


#: what kernels never import: the graph library, the stores, the configuration
NOT_IN_KERNELS = ("dask", "distributed", "zarr", "yaml", "pydantic")


def test_kernels_import_no_dask_stores_or_configuration():
    """Kernels are numpy/scipy (deferred ``distributed.get_worker`` in ``threads`` aside: base layer)."""
    bad = []
    for name, path in MODULES.items():
        if layer_of(name)[0] != "kernels":
            continue
        for node in ast.walk(parsed(path)):
            mods = ([a.name for a in node.names] if isinstance(node, ast.Import)
                    else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
            bad += [f"{name} imports {m} (line {node.lineno})" for m in mods if m.split(".")[0] in NOT_IN_KERNELS]
    assert not bad, "\n" + "\n".join(bad)


@pytest.mark.parametrize("region", REGIONS)
def test_no_private_name_imported_across_modules(region):
    bad = private_imports(_edges_in(region))
    assert not bad, "\n" + "\n".join(bad)


def uncommented_deferred_imports(root):
    """Function-level imports carrying no ``# deferred: <why>`` comment, as ``'module:line: text'``.

    An import inside a function (or method) is commented when ``# deferred:`` is on one of its
    lines, or the line right above it is a comment starting with ``# deferred:``, or it follows a
    commented import of the same indentation directly (no line between: one comment covers a block).
    """
    out = []
    for name, path in module_files(root).items():
        lines = path.read_text().splitlines()
        found = []

        def walk(node, in_function):
            for child in ast.iter_child_nodes(node):
                if in_function and isinstance(child, (ast.Import, ast.ImportFrom)):
                    found.append(child)
                walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

        walk(parsed(path), False)
        covered_ends = set()
        for node in sorted(found, key=lambda n: n.lineno):
            own = any("# deferred:" in line for line in lines[node.lineno - 1:node.end_lineno])
            above = lines[node.lineno - 2].strip() if node.lineno > 1 else ""
            if own or above.startswith("# deferred:") or (node.lineno - 1, node.col_offset) in covered_ends:
                covered_ends.add((node.end_lineno, node.col_offset))
            else:
                out.append(f"{name}:{node.lineno}: {lines[node.lineno - 1].strip()}")
    return out


def test_every_deferred_import_says_why():
    """Imports go at the top of a module; one inside a function is kept only for an optional or
    slow-to-import dependency most callers never need, with a ``# deferred: <why>`` comment
    (docs/architecture.md)."""
    bad = uncommented_deferred_imports(ROOT)
    assert not bad, "\nmove these to the top of the module, or add '# deferred: <why>':\n" + "\n".join(bad)


def test_stage_modules_import_no_other_stage():
    bad = [f"{a} -> {b} (line {line})" for a, b, line, _ in EDGES
           if stage_of(a) and stage_of(b) and stage_of(a) != stage_of(b)]
    assert not bad, "\n" + "\n".join(bad)


def test_every_stage_is_a_package_that_owns_its_stage_and_cost_model():
    """``stages/<name>/`` for every stage of the pipeline (no loose stage modules), each defining
    ``STAGE`` with its cost model; the planner asks the stage, never branches on its name."""
    import importlib

    from mmflow.workflow.pipeline import PIPELINE

    stages_dir = ROOT / "workflow" / "stages"
    packages = sorted(p.name for p in stages_dir.iterdir() if (p / "__init__.py").exists())
    assert packages == sorted(PIPELINE.names)
    assert sorted(p.name for p in stages_dir.glob("*.py")) == ["__init__.py", "base.py"]
    for st in PIPELINE.stages:
        own = importlib.import_module(f"mmflow.workflow.stages.{st.name}").STAGE
        assert own.name == st.name and own.cost is st.cost and own.task is st.task
        assert st.cost is not None and callable(st.cost.work), f"stage {st.name} has no cost model"


def test_the_schema_takes_each_stage_section_from_its_package():
    """The workflow schema is the shared sections plus every stage package's ``SECTIONS``, in run
    order, each class the package's own: no section is declared in ``config/`` for one stage."""
    import importlib

    from mmflow.workflow.config import schema
    from mmflow.workflow.pipeline import PIPELINE
    from mmflow.workflow.stages import ORDER

    assert PIPELINE.names == ORDER
    owned = {}
    for name in ORDER:
        path = ROOT / "workflow" / "stages" / name / "settings.py"
        if path.exists():
            module = importlib.import_module(f"mmflow.workflow.stages.{name}.settings")
            assert module.SECTIONS, f"{path.name} of {name} declares no SECTIONS"
            for section, cls in module.SECTIONS.items():
                assert cls.__module__ == module.__name__ and section not in owned
                owned[section] = cls
    fields = schema.WorkflowConfig.model_fields
    assert [k for k in fields if k in owned] == list(owned)  # run order
    assert all(fields[k].annotation is c for k, c in owned.items())
    shared = set(fields) - set(owned)
    assert shared == {"run", "source", "telescope", "beam", "observation", "cluster"}
    assert {"calibrate", "mmode", "imaging", "input", "sky", "corrupt"} <= set(owned)


def test_no_comparison_with_a_stage_name_outside_the_pipeline():
    """``if stage == "clean"`` elsewhere is a second copy of what the stage itself should say."""
    import re

    from mmflow.workflow.pipeline import PIPELINE

    names = "|".join(PIPELINE.names)
    pattern = re.compile(r"\bstage(?:\.name|_name)?\s*(?:==|!=|in|not in)\s*[(\[{]?\s*[\"'](%s)[\"']" % names)
    bad = []
    for path in ROOT.rglob("*.py"):
        if path.name == "pipeline.py":
            continue
        for i, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#", 1)[0]
            if pattern.search(code) and not code.lstrip().startswith("for "):  # a test, not a loop
                bad.append(f"{path.relative_to(ROOT.parent)}:{i}: {line.strip()}")
    assert not bad, "branches on a stage's name (give the stage the behaviour instead):\n" + "\n".join(bad)


def test_stores_are_named_through_their_declaration():
    """No ``"*.zarr"`` string in the package but the declarations of :data:`mmflow.io.run_stores.STORES`:
    readers and writers name a store as ``STORES.gains``, so a renamed or misspelt store fails at import."""
    import io
    import re
    import tokenize

    bad = []
    for path in ROOT.rglob("*.py"):
        toks = tokenize.generate_tokens(io.StringIO(path.read_text()).readline)
        for tok in toks:
            if tok.type == tokenize.STRING and re.fullmatch(r"[rbu]?([\"'])\w+\.zarr\1", tok.string):
                line = tok.line.strip()
                if path.name == "run_stores.py" and "= StoreName(" in line:
                    continue
                bad.append(f"{path.relative_to(ROOT.parent)}:{tok.start[0]}: {line}")
    assert not bad, "store names as literals (use mmflow.io.run_stores.STORES):\n" + "\n".join(bad)


# --- the checker itself can fail -------------------------------------------------------------

def test_walker_finds_a_deferred_cycle_and_an_upward_import(tmp_path):
    pkg = tmp_path / "mmflow"
    for d in ("mmode", "imaging", "io"):
        (pkg / d).mkdir(parents=True)
        (pkg / d / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "mmode" / "engine.py").write_text("import numpy\n\ndef f():\n    from ..imaging import maps\n")
    (pkg / "imaging" / "maps.py").write_text("from mmflow.mmode.engine import g as _g\n"
                                             "from mmflow.io.stores import _write\n")
    (pkg / "io" / "stores.py").write_text("import mmflow.mmode.engine\n")
    modules, edges = import_edges(pkg)
    assert set(modules) == {"mmflow", "mmflow.mmode", "mmflow.imaging", "mmflow.io", "mmflow.mmode.engine",
                            "mmflow.imaging.maps", "mmflow.io.stores"}
    pairs = {(a, b) for a, b, _, _ in edges}
    assert ("mmflow.mmode.engine", "mmflow.imaging.maps") in pairs       # deferred, relative
    assert cycles(modules, pairs) == [["mmflow.imaging.maps", "mmflow.io.stores", "mmflow.mmode.engine"]]
    assert upward(edges) == ["mmflow.imaging.maps -> mmflow.io.stores (line 2)"]
    assert private_imports(edges) == ["mmflow.imaging.maps imports _write from mmflow.io.stores (line 2)"]
    assert stage_of("mmflow.workflow.stages.base") is None and stage_of("mmflow.workflow.stages") is None
    assert stage_of("mmflow.workflow.stages.clean.stage") == "clean"
    assert stage_of("mmflow.workflow.stages.peel.solve") == stage_of("mmflow.workflow.stages.peel") == "peel"


def test_deferred_import_checker_flags_uncommented_imports(tmp_path):
    pkg = tmp_path / "mmflow"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("import json\n")                    # module level: fine
    (pkg / "m.py").write_text(
        "import os\n"
        "\n"
        "def a():\n"
        "    import numpy  # deferred: on its line\n"
        "\n"
        "def b():\n"
        "    # deferred: on the line above, for the block below\n"
        "    from astropy.coordinates import ICRS\n"
        "    from astropy.time import (\n"
        "        Time)\n"
        "    import casacore\n"
        "\n"
        "    import pyuvdata\n"                                           # 13: a blank line ends the block
        "\n"
        "def c():\n"
        "    x = 1\n"
        "    from mmflow import sub\n"                                    # 17
        "    import zarr  # deferred (no colon)\n"                        # 18
        "\n"
        "class K:\n"
        "    import re\n"                                                 # class body: not a function
        "\n"
        "    def m(self):\n"
        "        def inner():\n"
        "            from . import sub  # deferred: nested functions count too\n"
        "        import yaml\n")                                          # 26
    assert uncommented_deferred_imports(pkg) == ["mmflow.m:13: import pyuvdata", "mmflow.m:17: from mmflow import sub",
                                                 "mmflow.m:18: import zarr  # deferred (no colon)",
                                                 "mmflow.m:26: import yaml"]


# --- array names through their declaration ---------------------------------------------------

#: calls that open a zarr group (``ctx.open``, ``ctx.create``, ``spec.create``, ``zarr.open_group``,
#: ``open_checked``): a name they are assigned to, in the same function, is a group
GROUP_CALLS = {"open", "create", "open_group", "open_checked"}
#: parameters that hold a group by the package's naming (``g``: a store's group, ``vg``: vis.zarr's, ...)
GROUP_PARAMS = {"g", "vg", "mg", "ng", "pg", "group"}
#: calls that take an array's name: ``ctx.read(array, region)``; ``ctx.write(group, name, ...)``,
#: ``ctx.array(group, name)``, ``ChunkLedger.write(group, name, ...)`` / ``write_all``
NAME_SECOND = {"write", "array", "write_all"}
#: zarr's calls that create an array by name (``StoreSpec.create`` is the one that should)
NAME_FIRST = {"create_array", "require_array", "create_dataset", "require_dataset"}


def _is_literal(node):
    """A string written in the code: ``"gains"``, ``f"f{fi}/rhs"``, ``"f%d" % fi``, ``"f{}".format(fi)``."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, str)
    if isinstance(node, ast.JoinedStr):
        return True
    if isinstance(node, ast.BinOp):
        return _is_literal(node.left)
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "format"
            and _is_literal(node.func.value))


def _opens_group(node):
    f = node.func if isinstance(node, ast.Call) else None
    return f is not None and (f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)) in GROUP_CALLS


FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)


def _own_nodes(scope):
    """The nodes of a function (or module) outside the functions nested in it."""
    for child in ast.iter_child_nodes(scope):
        if not isinstance(child, FUNCTIONS):
            yield child
            yield from _own_nodes(child)


def _names_a_literal(node, groups):
    """Whether ``node`` names an array by a string (see :func:`array_name_literals`)."""
    def is_group(n):
        return (isinstance(n, ast.Name) and n.id in groups) or _opens_group(n)

    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
        args, attr = node.args, node.func.attr
        return ((attr == "read" and any(_is_literal(a) for a in args[:2]))
                or (attr in NAME_SECOND and len(args) >= 2 and _is_literal(args[1]))
                or (attr in NAME_FIRST and bool(args) and _is_literal(args[0])))
    if isinstance(node, ast.Subscript):
        return is_group(node.value) and _is_literal(node.slice)
    if isinstance(node, ast.Compare) and isinstance(node.ops[0], (ast.In, ast.NotIn)):
        return is_group(node.comparators[0]) and _is_literal(node.left)
    return False


def array_name_literals(root, declarations=("io/run_stores.py",)):
    """Array names written as strings where a store is read or written, as ``'path:line: code'``.

    Flagged: a literal as the array of ``X.read(...)`` (first or second argument), as the name
    (second argument) of ``X.write``/``X.array``/``X.write_all``, as the first argument of zarr's
    ``create_array`` and the like (:data:`NAME_FIRST`), as the key of ``group[...]`` or in
    ``... in group``, where ``group`` is a call opening one or a name bound to one in the function
    or one enclosing it (:data:`GROUP_CALLS`, :data:`GROUP_PARAMS`). ``declarations`` (relative to
    ``root``) are where the names are declared.
    """
    out = []
    for path in sorted(root.rglob("*.py")):
        if str(path.relative_to(root)) in declarations:
            continue
        found = set()

        def scan(scope, groups):
            own = list(_own_nodes(scope))
            if isinstance(scope, (ast.FunctionDef, ast.AsyncFunctionDef)):  # a lambda's g is not a group
                groups = groups | {a.arg for a in scope.args.args if a.arg in GROUP_PARAMS}
            groups = groups | {t.id for n in own if isinstance(n, ast.Assign) and _opens_group(n.value)
                               for t in n.targets if isinstance(t, ast.Name)}
            found.update(n.lineno for n in own if _names_a_literal(n, groups))
            for node in [scope, *own]:
                for child in ast.iter_child_nodes(node):
                    if isinstance(child, FUNCTIONS):
                        scan(child, groups)

        scan(parsed(path), frozenset())
        lines = path.read_text().splitlines()
        out += [f"{path.relative_to(root.parent)}:{i}: {lines[i - 1].strip()}" for i in sorted(found)]
    return out


def test_arrays_are_named_through_their_declaration():
    """Readers and writers name an array by its handle (``ctx.read(STORES.gains.gains, rows)``,
    ``g[STORES.normal.gram(fi, m0)]``: :data:`mmflow.io.run_stores.ARRAYS`), never by a string, so a
    renamed or misspelt array fails at the call, not as a missing array deep in a task."""
    bad = array_name_literals(ROOT)
    assert not bad, "array names as strings (use STORES.<store>.<array>):\n" + "\n".join(bad)


def test_array_name_checker_flags_literals(tmp_path):
    pkg = tmp_path / "mmflow"
    (pkg / "io").mkdir(parents=True)
    (pkg / "io" / "run_stores.py").write_text('ARRAYS = {"vis": ("vis",)}\nx = g["vis"]\n')   # the declarations
    (pkg / "m.py").write_text(
        "def a(ctx, g, fi):\n"
        "    ctx.read(STORES.gains.gains, (slice(0, 1),))\n"                  # a handle: fine
        "    ctx.read(STORES.gains, 'gains')\n"                               # 3
        "    ctx.write(g, f'f{fi}/rhs', (), 0)\n"                             # 4
        "    x = g['lst'][:]\n"                                               # 5
        "    d = {'lst': 1}\n"
        "    y = d['lst']\n"                                                  # a dict: fine
        "    fh.write('text')\n"                                              # one argument: fine
        "\n"
        "def b(ctx):\n"
        "    vis = ctx.open(STORES.vis)\n"
        "    n = vis['vis'].shape\n"                                          # 12
        "    c = 'vis_cross' in vis\n"                                        # 13
        "    m = ctx.open(STORES.alm)['alm']\n"                               # 14
        "    z = vis.attrs['epoch_jd']\n"                                     # attributes: fine
        "    ctx.array(vis, 'f%d/x' % 3)\n"                                   # 16
        "    return vis[STORES.vis.vis], ctx.read('vis.zarr/lst')\n"         # 17
        "\n"
        "root.create_array(f'chol_b{0:05d}', shape=(1,))\n")                 # 19
    assert [s.split(":")[1] for s in array_name_literals(pkg)] == ["3", "4", "5", "12", "13", "14", "16", "17", "19"]
