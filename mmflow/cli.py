"""``mmflow`` command line: run workflows, single stages, status, verify, config, stores and benchmarks."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

from mmflow import __version__, bench
from mmflow.allocator import keep_freed_memory
from mmflow.errors import InputError, MmflowError

BENCHMARKS = ("transfer", "solve", "simulate", "workflow", "calibrate", "ingest", "gaps", "clean", "channel", "table1",
              "paper", "cluster", "stokes-block")


def _common(p):
    p.add_argument("workflow", help="workflow YAML (see workflows/)")
    p.add_argument("overrides", nargs="*", help="section.key=value overrides")
    p.add_argument("--scheduler", help="join an existing dask scheduler (or set DASK_SCHEDULER_ADDRESS)")
    p.add_argument("--cluster", choices=("local", "slurm", "pbs", "synchronous"), help="override cluster.kind")
    p.add_argument("--force", action="store_true",
                   help="recompute stages whose inputs or settings changed (up-to-date stages are kept)")
    p.add_argument("--no-progress", action="store_true", help="no progress lines")


def build_parser(stages=True):
    """The command line; ``stages=False`` leaves out the per-stage subcommands (and the ~3 s import
    of every stage they are listed from) for a command that is not one of them."""
    ap = argparse.ArgumentParser(prog="mmflow", description=__doc__)
    ap.add_argument("--version", action="version", version=f"mmflow {__version__}")
    sub = ap.add_subparsers(dest="cmd")
    _common(sub.add_parser("run", help="run every enabled stage of a workflow"))
    if stages:
        # deferred: the stages load healpy, zarr and pydantic (~3 s): `import mmflow.cli` stays light
        from mmflow.workflow.pipeline import PIPELINE

        for st in PIPELINE:  # the one list of stages drives the subcommands
            _common(sub.add_parser(st.name, help=f"run only the '{st.name}' stage: {st.description}"))
    pl = sub.add_parser("plan", help="before a run: tasks, memory per task, disk and time of every stage")
    pl.add_argument("workflow", help="workflow YAML (see workflows/)")
    pl.add_argument("overrides", nargs="*", help="section.key=value overrides")
    pl.add_argument("--json", action="store_true", help="print the plan as JSON")
    pl.add_argument("--fit", nargs="+", metavar="RUN",
                    help="fit the cost constants to finished runs (run directories or --record files) and write "
                    "them to --costs (no plan printed)")
    pl.add_argument("--record", metavar="RUN_DIR",
                    help="print what a finished run measured (its configuration; per stage tasks, the largest "
                    "task's memory, seconds per task) as JSON: a record --fit and --against take like the run")
    pl.add_argument("--costs", help="constants file to read (or write with --fit); default: the package's")
    pl.add_argument("--peak", type=float, metavar="GFLOPS",
                    help="plan at this SGEMM peak (GFLOP/s) instead of the one measured now (e.g. the peak "
                    "measured beside a run, for --against); with --record, the peak measured beside the run")
    pl.add_argument("--against", metavar="RUN",
                    help="a finished run (directory or --record file): its configuration's plan beside what it "
                    "measured, per stage (the "
                    "workflow argument is ignored: give any)")
    pl.add_argument("--simulate-layout", action="store_true",
                    help="plan an ingesting workflow without its files: its own array (telescope), one sidereal "
                    "day of observation.integration_s, observation.freqs_mhz, the parallel hands")
    bc = pl.add_argument_group("cluster", "lay the run onto a batch cluster's nodes (docs/clusters.md, "
                               "'Sizing jobs from the plan')")
    bc.add_argument("--cluster", choices=("slurm", "pbs"),
                    help="per stage the job shape (cores, memory, walltime) and count, the nodes, disk and wall time")
    bc.add_argument("--node-cores", type=int, metavar="N", help="cores of a node (default: from sinfo)")
    bc.add_argument("--node-memory", metavar="BYTES", help="memory a job may use on a node, e.g. 128GB "
                    "(default: from sinfo)")
    bc.add_argument("--nodes", type=int, metavar="K", help="nodes to plan on (default: the fewest within 10 %% "
                    "of the fastest)")
    bc.add_argument("--partition", help="the SLURM partition whose nodes sinfo gives (default: the default one)")
    bc.add_argument("--node-peak", type=float, metavar="GFLOPS",
                    help="a node's SGEMM peak, all its cores (default: this machine's per core)")
    bc.add_argument("--project", type=int, nargs="+", metavar="K",
                    help="print, as JSON, the plan projected onto each of these node counts (wall time, a node's "
                    "memory, stores, jobs)")
    st = sub.add_parser("status", help="stages and chunks done in a run directory, STALE ones flagged")
    st.add_argument("run_dir")
    vf = sub.add_parser("verify", help="check every recorded chunk of a run directory (sizes and XXH3 checksum)")
    vf.add_argument("run_dir")
    vf.add_argument("--quick", action="store_true", help="sizes only, no checksums")
    cf = sub.add_parser("config", help="show the schema or write a starting workflow")
    cf.add_argument("action", choices=("show", "init"))
    cf.add_argument("path", nargs="?", help="for init: where to write the YAML")
    so = sub.add_parser("stores", help="the zarr stores of a run directory as markdown (docs/stores.md)")
    so.add_argument("action", choices=("show",))
    b = sub.add_parser("bench", help="benchmarks that print JSON figures")
    b.add_argument("what", choices=BENCHMARKS)
    b.add_argument("--quick", action="store_true", help="smaller sizes (for CI smoke runs)")
    b.add_argument("--output", help="also write the JSON here")
    ch = b.add_argument_group("channel", "options of `mmflow bench channel` (defaults: the paper's channel)")
    ch.add_argument("--layout", default="paper-2017", help="OVRO-LWA layout preset")
    ch.add_argument("--freq-mhz", type=float, default=73.152, help="frequency in MHz")
    ch.add_argument("--lmax", type=int, help="lmax (default 1000; 128 with --quick)")
    ch.add_argument("--scale", help="fractions of the baseline chunks to run, comma-separated (1: the full "
                    "channel; default 0.02,0.05; 0.05 with --quick)")
    ch.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    ch.add_argument("--workflow", action="store_true",
                    help="also run the workflow's transfer/normal/solve stages on a local cluster")
    ch.add_argument("--engine-only", action="store_true", help="only the engine (the default; overrides --workflow)")
    ch.add_argument("--workers", type=int, default=1, help="local worker processes for --workflow")
    ch.add_argument("--solve-stride", type=int, default=1, help="solve every N-th m (the rest projected by n^3)")
    tr = b.add_argument_group("transfer", "options of `mmflow bench transfer`")
    tr.add_argument("--stokes", choices=("I", "IQUV"), default="I",
                    help="IQUV: full-Stokes transfer + Gram against Stokes I in the same run (docs/stokes.md)")
    sb = b.add_argument_group("stokes-block", "options of `mmflow bench stokes-block` (the paper's channel in full "
                              "Stokes; --set for further overrides)")
    sb.add_argument("--fraction", type=int, help="measure 1/N of the baselines (default 128; 8 with --quick)")
    sb.add_argument("--blocks", help="the blocks of m to run, comma-separated indices (default every block)")
    ig = b.add_argument_group("ingest", "options of `mmflow bench ingest`")
    ig.add_argument("--raw", action="store_true",
                    help="raw OVRO-LWA MeasurementSets (one per integration, 109 channels, xx yy xy yx, uncalib): "
                    "one channel kept and four averaged, beside pyuvdata's reads")
    cl = b.add_argument_group("cluster", "options of `mmflow bench cluster`")
    cl.add_argument("--cluster-workflow", dest="cluster_workflow", choices=("demo", "paper", "array"), default="demo",
                    help="demo (default): the demo on one exclusive 1-core job a node; paper: workflows/paper-scale"
                    ".yaml reduced; array: the 352-antenna workflows/ovro-lwa-stage3.yaml reduced (paper and array "
                    "on jobs sized per stage from the plan, each stage's traced task peak beside the plan's)")
    cl.add_argument("--node-memory-mb", type=int, default=3000, help="each namespaced node's memory (MB)")
    cl.add_argument("--nodes", dest="cluster_nodes", default="1,2,3", help="node counts to run on, comma-separated")
    cl.add_argument("--no-reference", dest="cluster_reference", action="store_false",
                    help="skip the synchronous reference run (the plan against the traced peaks only: no bit "
                    "comparison, `identical` null)")
    pp = b.add_argument_group("paper", "options of `mmflow bench paper` (workflows/paper-scale.yaml)")
    pp.add_argument("--paper-scale", choices=("full", "reduced", "small"),
                    help="full: the paper's channel (default); reduced: 64 antennas, 1/8 of the integrations, "
                    "lmax 200 (--quick); small: 32 antennas, 1/16, lmax 100")
    pp.add_argument("--paper-source", choices=("ingest", "simulate"), default="ingest",
                    help="ingest (default): the simulate stage first writes the telescope's UVH5 files, the "
                    "measured run reads them; simulate: the workflow simulates straight into vis.zarr")
    pp.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="further workflow overrides, e.g. observation.freqs_mhz=[62.688,73.152]")
    return ap


#: commands (and options) that are not a stage: their parser need not list the stages
NOT_STAGES = ("--version", "plan", "status", "verify", "config", "stores", "bench")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(stages=not (argv and argv[0] in NOT_STAGES))
    args, extra = parser.parse_known_args(argv)
    if extra:  # options and overrides in any order: `mmflow run wf.yaml --no-progress key=value`
        if not hasattr(args, "overrides") or any(x.startswith("-") or "=" not in x for x in extra):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = [*args.overrides, *extra]
    if args.cmd is None:
        parser.print_help()
        return 0
    keep_freed_memory()  # the same allocator settings as mmflow's tasks in dask workers (mmflow.allocator)
    try:
        return _dispatch(args)
    except MmflowError as exc:
        print(f"mmflow: error: {exc}", file=sys.stderr)
        return 2


def _status(args):
    from mmflow.workflow.engine.runner import status  # deferred: workflow modules (~3 s)

    for name, s in status(args.run_dir).items():
        if s is None:
            print(f"{name:12s} not started")
            continue
        extra = f"  {s['summary']['wall_s']} s" if s["summary"] else ""
        stale = "  STALE: made from other settings (rerun with --force)" if s["stale"] else ""
        gone = f"  released: {', '.join(s['released'])}" if s["released"] else ""
        print(f"{name:12s} {s['done']}/{s['total']} chunks {'complete' if s['complete'] else 'incomplete'}"
              f"{extra}{gone}{stale}")
    return 0


def _verify(args):
    from mmflow.workflow.engine.runner import verify  # deferred: workflow modules (~3 s)

    bad = 0
    for name, problems in verify(args.run_dir, full=not args.quick).items():
        print(f"{name:12s} {'ok' if not problems else f'{len(problems)} problems'}")
        for p in problems[:20]:
            print(f"    {p}")
        bad += len(problems)
    if bad:
        print(f"{bad} problems: rerun the workflow with --force to recompute the damaged stages", file=sys.stderr)
    return 1 if bad else 0


def _config(args):
    from mmflow.workflow.config.schema import schema_yaml  # deferred: workflow modules (~3 s)

    text = schema_yaml()
    if args.action == "init":
        if not args.path:
            raise InputError("config init", "path", "no file name given", "write `mmflow config init my-workflow.yaml`")
        path = Path(args.path)
        if path.exists():
            raise InputError(str(path), "file", "exists already (it is never overwritten)",
                             "give a new file name, or remove the old file yourself")
        default_dir = yaml.safe_load(text)["run"]["directory"]
        text = text.replace(f"directory: {default_dir}", f"directory: runs/{path.stem}", 1)  # its own run directory
        path.write_text(text)
        print(f"wrote {path} (runs into runs/{path.stem}; edit it, then `mmflow run {path}`)")
    else:
        print(text, end="")
    return 0


def _stores(args):
    from mmflow.io.store_docs import stores_markdown  # deferred: zarr (~1 s): `import mmflow.cli` stays light
    from mmflow.workflow.pipeline import PIPELINE  # the stages that write and read each store

    print(stores_markdown(PIPELINE.lifetimes()), end="")
    return 0


def _bench(args):
    options = {}
    if args.what == "channel":
        options = dict(layout=args.layout, freq_mhz=args.freq_mhz, lmax=args.lmax, dtype=args.dtype,
                       scales=[float(x) for x in args.scale.split(",")] if args.scale else None,
                       workflow=args.workflow and not args.engine_only, workers=args.workers,
                       solve_stride=args.solve_stride)
    elif args.what == "paper":
        options = dict(scale=args.paper_scale, overrides=args.set, source=args.paper_source)
    elif args.what == "cluster":
        options = dict(workflow=args.cluster_workflow, node_memory_mb=args.node_memory_mb,
                       nodes=tuple(int(n) for n in args.cluster_nodes.split(",")), reference=args.cluster_reference)
    elif args.what == "ingest":
        options = dict(raw=args.raw)
    elif args.what == "transfer":
        options = dict(stokes=args.stokes)
    elif args.what == "stokes-block":
        options = dict(fraction=args.fraction, overrides=args.set,
                       blocks=[int(x) for x in args.blocks.split(",")] if args.blocks else None)
    res = bench.run(args.what, quick=args.quick, **options)
    text = json.dumps(res, indent=2)
    print(text)
    if args.output:
        with open(args.output, "w") as fh:
            fh.write(text)
    return 0


def _plan(args):
    from mmflow.workflow.plan import planner as planmod  # deferred: workflow modules (~3 s)

    if args.fit:
        # deferred: scipy's BLAS and workflow modules (~3 s): `import mmflow.cli` stays light
        from mmflow.machine import gemm_gflops
        from mmflow.workflow.plan.fit import fit_costs, reference_peak, write_costs

        path = args.costs or planmod.COSTS_FILE
        write_costs(fit_costs(args.fit, reference_peak(args.fit, lambda: gemm_gflops(np.float32, n=768))), path)
        print(f"wrote {path}")
        return 0
    if args.record:
        from mmflow.workflow.plan.fit import record  # deferred: workflow modules (~3 s)

        print(json.dumps(record(args.record, args.peak), indent=1))
        return 0
    if args.against:
        from mmflow.workflow.plan.fit import format_against, plan_against_run  # deferred: workflow modules (~3 s)

        rows, peak = plan_against_run(args.against, planmod.load_costs(args.costs) if args.costs else None,
                                      args.peak)
        print(json.dumps({"sgemm_gflops": peak, "stages": rows}, indent=2, default=float) if args.json
              else format_against(rows, peak))
        return 0
    from mmflow.workflow.config.schema import load_config  # deferred: workflow modules (~3 s)

    cfg = load_config(args.workflow, args.overrides)
    costs = planmod.load_costs(args.costs) if args.costs else None
    ingest = None
    if args.simulate_layout:
        from mmflow.workflow.plan.jobs import layout_ingest  # deferred: workflow modules (~3 s)

        ingest = layout_ingest(cfg)
    try:
        if args.cluster:
            from mmflow.workflow.plan import jobs, nodes  # deferred: workflow modules (~3 s)

            node = nodes.node_size(args.node_cores, args.node_memory, args.partition, scheduler=args.cluster)
            if args.project:
                print(json.dumps(jobs.projection(cfg, node, args.project, costs=costs, peak_gflops=args.peak,
                                                 node_gflops=args.node_peak, ingest=ingest), indent=2))
                return 0
            res = jobs.cluster_plan(cfg, node, args.nodes, costs, args.peak, args.node_peak, ingest)
            print(json.dumps(res, indent=2, default=float) if args.json else jobs.format_cluster_plan(res))
            return 0
        res = planmod.plan(cfg, costs, args.peak, ingest)
    except InputError as exc:
        if exc.field != "input.path" or ingest is not None:
            raise
        raise InputError(exc.what, exc.field, exc.problem, f"{exc.fix}; or plan the workflow's own array without "
                         "its files: --simulate-layout") from None
    print(json.dumps(res, indent=2, default=float) if args.json else planmod.format_plan(res))
    return 0


def _dispatch(args):
    handlers = {"status": _status, "verify": _verify, "config": _config, "stores": _stores, "bench": _bench,
                "plan": _plan}
    if args.cmd in handlers:
        return handlers[args.cmd](args)
    # deferred: workflow modules (~3 s)
    from mmflow.workflow.engine.cluster import open_cluster
    from mmflow.workflow.engine.passes import run_with_passes

    cfg = _run_config(args)
    only = None if args.cmd == "run" else [args.cmd]
    with open_cluster(cfg, args.scheduler, args.cluster) as client:
        summaries = run_with_passes(cfg, client, only=only, force=args.force, progress=not args.no_progress)
    _report(cfg, summaries)
    return 0


def _run_config(args, log=print):
    """The workflow a run command runs: the file, its overrides, ``--cluster`` / ``--scheduler`` as
    ``cluster.kind`` (recorded as such in the run's config.yaml), and on a batch cluster whose jobs are
    sized per stage the settings that split a task too large for its nodes
    (:func:`mmflow.workflow.engine.pools.split_to_fit`), as overrides after the user's."""
    from mmflow.workflow.config.schema import load_config  # deferred: workflow modules (~3 s)
    from mmflow.workflow.engine.pools import split_to_fit  # deferred: workflow modules

    chosen = [f"cluster.kind={args.cluster}"] if args.cluster else \
        ["cluster.kind=address", f"cluster.address={args.scheduler}"] if args.scheduler else []
    cfg = load_config(args.workflow, [*args.overrides, *chosen])
    if cfg.cluster.kind in ("slurm", "pbs"):
        split = split_to_fit(cfg, cfg.cluster.kind, log)
        if split:
            cfg = load_config(args.workflow, [*args.overrides, *chosen, *(f"{k}={v}" for k, v in split.items())])
    return cfg


def _report(cfg, summaries):
    """What a user checks first: where the maps are, their resolution, rms and fraction of modes, stage times."""
    run = Path(cfg.run.directory).absolute()
    print("stage times: " + ", ".join(f"{k} kept ({v['tasks']} tasks done before)" if v.get("kept") else
                                      f"{k} {v['wall_s']} s ({v['tasks_run']}/{v['tasks']} tasks run)"
                                      for k, v in summaries.items()))
    summary = run / "maps" / "summary.json"
    if not summary.exists():
        return
    if "products" not in summaries and any(v["tasks_run"] > 0 for v in summaries.values()):
        print("maps below are STALE: made before the stages this command recomputed (`mmflow run` refreshes them)")
    for m in json.loads(summary.read_text())["maps"]:
        ratio = m.get("chosen_over_corner_eps")
        print(f"{m['freq_hz'] / 1e6:.3f} MHz: {run / m['fits']}"
              + (f" (+ {run / m['png']})" if m.get("png") else "")
              + f"\n    resolution ~{m['resolution_deg'] * 60:.0f}' | rms {m['map_rms']:.4g} {m['unit']} over the "
              f"{m['sky_fraction_seen']:.0%} of the sky seen | singular values above sqrt(eps): "
              f"{m['fraction_singular_values_above_sqrt_eps']:.1%}"
              + (f" | eps is {ratio:.3g}x the L-curve corner" if ratio else ""))
    print(f"log: {run / 'mmflow.log'}")


if __name__ == "__main__":
    sys.exit(main())
