"""The ``/mmflow`` page of the dask dashboard, and the dashboard's address as it really listens.

The page is a route of the scheduler's HTTP server, the one that serves dask's ``/status``: this
module is one of dask's ``distributed.scheduler.http.routes`` (each such module names its
``routes``; dask hands every handler the scheduler). :func:`serve_page` adds it before a
cluster starts. ``/mmflow`` is plain HTML that reloads itself every :data:`REFRESH_S` seconds
(no script, nothing fetched from elsewhere); ``/mmflow.json`` is the same for programs.
"""
from __future__ import annotations

import html
import ipaddress
from urllib.parse import urlparse

import dask
from distributed.http.utils import RequestHandler
from distributed.utils import format_dashboard_link, get_ip

from mmflow.workflow.engine.dashboard.board import BOARD, seconds_left

#: dask's list of modules whose ``routes`` its scheduler serves
ROUTES_KEY = "distributed.scheduler.http.routes"
#: the page, relative to the dashboard's root (beside dask's ``status``)
PAGE = "mmflow"
REFRESH_S = 2


def serve_page():
    """Add this module to dask's scheduler routes (idempotent): schedulers started afterwards in
    this process serve ``/mmflow`` and ``/mmflow.json``."""
    routes = list(dask.config.get(ROUTES_KEY, []))
    if __name__ not in routes:
        dask.config.set({ROUTES_KEY: routes + [__name__]})


def dashboard_link(cluster, client, page="status"):
    """The dashboard's ``page`` at the address its HTTP server is bound to.

    dask's ``client.dashboard_link`` puts the scheduler's host in front of the dashboard's port;
    on a batch cluster the scheduler listens on the cluster network while the dashboard listens
    on 127.0.0.1 only, so that link does not answer. Here the host is the dashboard's own bound
    address (the scheduler's host, or this machine's address, only where the dashboard listens on
    every interface). A cluster whose scheduler is not in this process (joined by address): dask's
    link. ``page`` replaces the link's final ``status`` (dask's ``distributed.dashboard.link``
    template is kept: scheme, proxy prefixes).
    """
    sched = getattr(cluster, "scheduler", None)
    http = getattr(sched, "http_server", None)
    port = getattr(http, "port", None)
    if port:
        host = http.address
        if ipaddress.ip_address(host).is_unspecified:  # 0.0.0.0 or ::: any of this machine's addresses
            host = urlparse(sched.address).hostname
            if not host or ipaddress.ip_address(host).is_unspecified:
                host = get_ip()
        link = format_dashboard_link(f"[{host}]" if ":" in host else host, port)
    else:
        link = client.dashboard_link
    if page != "status" and link.endswith("status"):
        link = link[: -len("status")] + page
    return link


def workers_of(scheduler):
    """The scheduler's workers as the page shows them: name, address, threads, tasks processing,
    process memory and memory limit (bytes)."""
    out = []
    for ws in scheduler.workers.values():
        out.append({"name": str(ws.name), "address": ws.address, "nthreads": ws.nthreads,
                    "processing": len(ws.processing), "memory": int(ws.memory.process),
                    "memory_limit": int(ws.memory_limit or 0)})
    return sorted(out, key=lambda w: w["address"])


def page_state(snapshot, workers):
    """The page's figures: the board's snapshot with the workers, the task slots (the workers'
    threads, else the configured ones), the plan's time left and the stage running now."""
    slots = sum(w["nthreads"] for w in workers) or snapshot["slots"]
    left, unknown = seconds_left(snapshot, slots)
    running = next((r for r in snapshot["stages"] if r["state"] == "running"), None)
    return dict(snapshot, workers=workers, task_slots=slots, seconds_left=left, unknown_time=unknown,
                running=running["name"] if running else None)


def _duration(s):
    """Seconds as ``mmflow plan`` prints them (s, min, h), with the tenths of a small run's tasks."""
    if s is None:
        return "?"
    s = float(s)
    if 0 < s < 10:  # a small run's tasks: a tenth of a second, not "0 s"
        return f"{s:.2f} s" if s < 1 else f"{s:.1f} s"
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.1f} h"


def _bar(frac, cls=""):
    """A horizontal bar filled to ``frac`` (0-1); ``cls``: ``over`` (red) or ``kept`` (grey)."""
    w = max(0.0, min(float(frac), 1.0)) * 100
    return f'<span class="track"><span class="fill {cls}" style="width:{w:.0f}%"></span></span>'


_CSS = """
body{font-family:sans-serif;margin:1em 2em;color:#222}h1{font-size:1.4em;margin:.2em 0}
table{border-collapse:collapse;margin:.5em 0 1.5em;font-size:.95em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}th{background:#f0f0f0}td.l,th.l{text-align:left}
.track{display:inline-block;width:160px;height:.8em;background:#eee;border:1px solid #bbb;vertical-align:middle}
.fill{display:block;height:100%;background:#4a7ab5}.fill.over{background:#c0392b}.fill.kept{background:#9ab}
.facts td{text-align:left}.stopped{color:#b00;font-weight:bold}
tr.running td{background:#fff6d5}
"""


def _stage_rows(state):
    rows = []
    slots = max(int(state["task_slots"] or 1), 1)
    for k, r in enumerate(state["stages"], 1):
        total = r["total"] if r["total"] is not None else r["planned_tasks"]
        frac = r["done"] / total if total else (1.0 if r["state"] in ("done", "kept") else 0.0)
        left, _ = seconds_left({"stages": [r], "slots": slots})
        elapsed = r["wall_s"] if r["wall_s"] is not None else (
            state["now"] - r["started"] if r["started"] is not None and r["state"] == "running" else None)
        left_text = "0 s" if r["state"] in ("done", "kept") else (
            "?" if r["task_seconds"] is None else _duration(left))
        count = f"{r['done']}/{total if total is not None else '?'}" + ("" if r["total"] is not None else " (plan)")
        per_task = "?" if r["task_seconds"] is None else _duration(r["task_seconds"])
        task_gb = "?" if r["task_gb"] is None else f"{r['task_gb']:.2f}"
        rows.append(
            f'<tr class="{r["state"]}"><td>{k}</td><td class="l">{html.escape(r["name"])}</td>'
            f'<td class="l">{r["state"]}</td><td class="tasks">{count}</td>'
            f'<td class="l">{_bar(frac, "kept" if r["state"] == "kept" else "")}</td>'
            f'<td>{per_task}</td><td>{"" if elapsed is None else _duration(elapsed)}</td>'
            f'<td class="left">{left_text}</td><td>{task_gb}</td></tr>')
    head = ("<tr><th>#</th><th class=l>stage</th><th class=l>state</th><th>tasks done</th><th class=l></th>"
            "<th>plan per task</th><th>elapsed</th><th>time left (plan)</th><th>plan task GB</th></tr>")
    return f'<table id="stages">{head}{"".join(rows)}</table>'


def _worker_rows(state):
    running = next((r for r in state["stages"] if r["name"] == state["running"]), None)
    task_gb, base_gb = (running or {}).get("task_gb"), state.get("worker_base_gb") or 0.0
    if not state["workers"]:
        return '<p id="workers">no dask worker connected (yet)</p>'
    rows = []
    for w in state["workers"]:
        plan_gb = None
        if task_gb is not None:  # the worker's baseline and each task it runs at once at the plan's largest
            plan_gb = base_gb + max(1, min(w["nthreads"], w["processing"])) * (task_gb - base_gb)
        mem, lim = w["memory"] / 1e9, w["memory_limit"] / 1e9
        over = plan_gb is not None and lim and plan_gb > lim
        plan_text, lim_text = "" if plan_gb is None else f"{plan_gb:.2f}", f"{lim:.2f}" if lim else "none"
        rows.append(
            f'<tr><td class="l">{html.escape(w["name"])}</td><td class="l">{html.escape(w["address"])}</td>'
            f'<td>{w["nthreads"]}</td><td>{w["processing"]}</td><td class="mem">{mem:.2f}</td>'
            f'<td>{plan_text}</td><td>{lim_text}</td>'
            f'<td class="l">{_bar(mem / lim if lim else 0.0, "over" if over else "")}</td></tr>')
    head = ("<tr><th class=l>worker</th><th class=l>address</th><th>threads</th><th>tasks running</th>"
            "<th>memory GB</th><th>plan GB</th><th>limit GB</th><th class=l>memory / limit</th></tr>")
    note = (f"plan GB: the worker's baseline and the plan's largest task of stage <b>{html.escape(running['name'])}"
            "</b> for each task it runs at once" if running else "plan GB: shown while a stage runs")
    return f'<table id="workers">{head}{"".join(rows)}</table><p>{note}</p>'


def render_page(state):
    """The page's HTML from :func:`page_state`."""
    if state["run_dir"] is None:
        status = "no mmflow run has started in this process yet"
    elif state["ended"] is None:
        status = f"running for {_duration(state['now'] - state['started'])}"
    elif state["error"]:
        status = f'<span class="stopped">stopped: {html.escape(state["error"])}</span>'
    else:
        status = f"finished in {_duration(state['ended'] - state['started'])}"
    left = "0 s" if state["ended"] is not None else _duration(state["seconds_left"])
    if state["unknown_time"] and state["ended"] is None:
        left += f" (and {', '.join(state['unknown_time'])}: no plan)"
    facts = [("run-dir", "run directory", html.escape(str(state["run_dir"] or ""))),
             ("cluster", "cluster", html.escape(str(state["cluster"] or ""))), ("status", "status", status),
             ("n-workers", "workers", f"{len(state['workers'])} ({state['task_slots']} task slots)"),
             ("time-left", "time left (plan)", left)]
    table = "".join(f'<tr><th class="l">{label}</th><td class="l" id="{i}">{v}</td></tr>' for i, label, v in facts)
    return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
            f'<meta http-equiv="refresh" content="{REFRESH_S}"><title>mmflow run</title><style>{_CSS}</style>'
            f'</head><body><h1>mmflow run</h1><p><a href="status">dask dashboard</a></p>'
            f'<table class="facts">{table}</table><h2>Stages</h2>{_stage_rows(state)}'
            f"<h2>Workers</h2>{_worker_rows(state)}</body></html>\n")


class MmflowPage(RequestHandler):
    """``GET /mmflow``: the run's stages and workers as HTML."""

    def get(self):
        self.set_header("Content-Type", "text/html; charset=utf-8")
        self.set_header("Cache-Control", "no-store")
        self.write(render_page(page_state(BOARD.snapshot(), workers_of(self.server))))


class MmflowJSON(RequestHandler):
    """``GET /mmflow.json``: the same figures as JSON."""

    def get(self):
        self.set_header("Cache-Control", "no-store")
        self.write(page_state(BOARD.snapshot(), workers_of(self.server)))


#: read by dask (``distributed.http.utils.get_handlers``) when a scheduler starts
routes = [(f"/{PAGE}", MmflowPage, {}), (f"/{PAGE}.json", MmflowJSON, {})]
