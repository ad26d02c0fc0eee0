"""``mmflow`` command line: run workflows, single stages, status, config and benchmarks."""
from __future__ import annotations

import argparse
import json
import sys

STAGE_COMMANDS = ("simulate", "ingest", "mmodes", "transfer", "normal", "solve", "products",
                  "calibrate", "peel", "terrestrial", "clean")


def _common(p):
    p.add_argument("workflow", help="workflow YAML (see workflows/)")
    p.add_argument("overrides", nargs="*", help="section.key=value overrides")
    p.add_argument("--scheduler", help="join an existing dask scheduler (or set DASK_SCHEDULER_ADDRESS)")
    p.add_argument("--cluster", choices=("local", "slurm", "pbs", "synchronous"), help="override cluster.kind")
    p.add_argument("--force", action="store_true", help="recompute stages whose inputs or settings changed")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def build_parser():
    ap = argparse.ArgumentParser(prog="mmflow", description=__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    _common(sub.add_parser("run", help="run every enabled stage of a workflow"))
    for name in STAGE_COMMANDS:
        _common(sub.add_parser(name, help=f"run only the '{name}' stage"))
    st = sub.add_parser("status", help="stages and chunks done in a run directory")
    st.add_argument("run_dir")
    cf = sub.add_parser("config", help="show the schema or write a starting workflow")
    cf.add_argument("action", choices=("show", "init"))
    cf.add_argument("path", nargs="?", help="for init: where to write the YAML")
    b = sub.add_parser("bench", help="benchmarks that print JSON figures")
    b.add_argument("what", choices=("transfer", "solve", "simulate"))
    b.add_argument("--quick", action="store_true", help="smaller sizes (for CI smoke runs)")
    b.add_argument("--output", help="also write the JSON here")
    return ap


def main(argv=None):
    args = build_parser().parse_args(argv)
    from mmflow.errors import MmflowError

    try:
        return _dispatch(args)
    except MmflowError as exc:
        print(f"mmflow: error: {exc}", file=sys.stderr)
        return 2


def _dispatch(args):
    if args.cmd == "status":
        from mmflow.workflow.runner import status

        st = status(args.run_dir)
        for name, s in st.items():
            if s is None:
                print(f"{name:12s} not started")
            else:
                extra = f"  {s['summary']['wall_s']} s" if s["summary"] else ""
                stale = "  STALE: made from other settings (rerun with --force)" if s["stale"] else ""
                print(f"{name:12s} {s['done']}/{s['total']} chunks "
                      f"{'complete' if s['complete'] else 'incomplete'}{extra}{stale}")
        return 0
    if args.cmd == "config":
        from mmflow.workflow.config import schema_yaml

        text = schema_yaml()
        if args.action == "init" and args.path:
            with open(args.path, "w") as fh:
                fh.write(text)
            print(f"wrote {args.path}")
        else:
            print(text, end="")
        return 0
    if args.cmd == "bench":
        from mmflow import bench

        res = bench.run(args.what, quick=args.quick)
        text = json.dumps(res, indent=2)
        print(text)
        if args.output:
            with open(args.output, "w") as fh:
                fh.write(text)
        return 0
    from mmflow.workflow.cluster import open_cluster
    from mmflow.workflow.config import load_config
    from mmflow.workflow.runner import run_workflow

    cfg = load_config(args.workflow, args.overrides)
    only = None if args.cmd == "run" else [args.cmd]
    with open_cluster(cfg, args.scheduler, args.cluster) as client:
        summaries = run_workflow(cfg, client, only=only, force=args.force, progress=not args.no_progress)
    print(json.dumps({k: {kk: v[kk] for kk in ("wall_s", "tasks", "tasks_run", "bytes_written")}
                      for k, v in summaries.items()}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
