"""The dashboard's run board and its page, without a cluster: what the driver tells it, what it shows."""
import re
from types import SimpleNamespace

import pytest

from mmflow.workflow.engine.dashboard.board import RunBoard, cluster_kind, seconds_left
from mmflow.workflow.engine.dashboard.page import page_state, render_page
from mmflow.workflow.plan.planner import WORKER_BASE_BYTES


def _estimate(stage, tasks, seconds, task_bytes):
    return SimpleNamespace(stage=stage, tasks=tasks, seconds=seconds, task_bytes=task_bytes)


@pytest.fixture
def board():
    now = [1000.0]
    b = RunBoard(clock=lambda: now[0])
    b.now = now
    plan = [_estimate("simulate", 4, 40.0, 1e9), _estimate("transfer", 2, 60.0, 3e9),
            _estimate("products", 1, 0.0, 0.5e9)]  # products: no fitted time
    b.begin_run("/runs/x", "slurm", ["simulate", "mmodes", "transfer", "products"], plan, slots=2)
    return b


def test_board_follows_the_run_in_pipeline_order(board):
    s = board.snapshot()
    assert [r["name"] for r in s["stages"]] == ["simulate", "mmodes", "transfer", "products"]
    sim = s["stages"][0]
    assert sim["planned_tasks"] == 4 and sim["task_seconds"] == 10.0
    assert sim["task_gb"] == pytest.approx((1e9 + WORKER_BASE_BYTES) / 1e9)
    assert s["stages"][1]["task_seconds"] is None  # complete before: no plan

    board.begin_stage("simulate", 4, 1)  # one task finished in an earlier run
    board.begin_batch("simulate")
    board.progress("simulate", 2)
    r = board.snapshot()["stages"][0]
    assert (r["state"], r["done"], r["total"]) == ("running", 3, 4)
    board.now[0] += 30
    board.finish_stage("simulate", 30.0)
    board.keep_stage("mmodes", 3)
    board.begin_stage("transfer", 2, 0)
    board.begin_batch("transfer")
    board.progress("transfer", 2)
    board.add_tasks("transfer", 3, done=1)  # a second phase: three more tasks, one done before
    board.begin_batch("transfer")
    board.progress("transfer", 1)
    s = board.snapshot()
    assert [(r["state"], r["done"], r["total"]) for r in s["stages"]] == [
        ("done", 4, 4), ("kept", 3, 3), ("running", 4, 5), ("waiting", 0, None)]
    board.end_run("MmflowError: no worker")
    s = board.snapshot()
    assert s["error"] == "MmflowError: no worker" and s["stages"][2]["state"] == "stopped"


def test_time_left_comes_from_the_plan_per_task_slot(board):
    s = board.snapshot()
    # simulate 4 tasks x 10 s on 2 slots, transfer 2 x 30 s; products has no fitted time
    assert seconds_left(s) == (2 * 10.0 + 1 * 30.0, ["products"])
    assert seconds_left(s, slots=1)[0] == 4 * 10.0 + 2 * 30.0
    board.begin_stage("simulate", 4, 0)
    board.begin_batch("simulate")
    board.progress("simulate", 3)
    assert seconds_left(board.snapshot())[0] == 10.0 + 30.0


def test_cluster_kind_of_a_client():
    assert cluster_kind(None) == "synchronous"
    assert cluster_kind(SimpleNamespace(kind="pbs")) == "pbs"
    assert cluster_kind(object()) == "address"  # a dask client made elsewhere


def _cells(page, table_id):
    table = re.search(rf'<table id="{table_id}">(.*?)</table>', page).group(1)
    rows = re.findall(r"<tr[^>]*>(.*?)</tr>", table)[1:]
    return [[re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", row)] for row in rows]


def test_page_shows_stages_workers_against_the_plan_and_escapes_text(board):
    board.begin_stage("simulate", 4, 0)
    board.begin_batch("simulate")
    board.progress("simulate", 1)
    board.now[0] += 12
    workers = [{"name": "<w0>", "address": "tcp://10.0.0.2:4000", "nthreads": 2, "processing": 2,
                "memory": int(1.5e9), "memory_limit": int(4e9)},
               {"name": "w1", "address": "tcp://10.0.0.3:4000", "nthreads": 2, "processing": 0,
                "memory": int(0.4e9), "memory_limit": int(2e9)}]
    state = page_state(board.snapshot(), workers)
    assert state["task_slots"] == 4 and state["running"] == "simulate"
    page = render_page(state)
    assert 'http-equiv="refresh"' in page and "<w0>" not in page and "&lt;w0&gt;" in page
    assert "/runs/x" in page and '<td class="l" id="cluster">slurm</td>' in page
    stages = _cells(page, "stages")
    assert [r[1] for r in stages] == ["simulate", "mmodes", "transfer", "products"]
    assert stages[0][2:4] == ["running", "1/4"] and stages[2][3] == "0/2 (plan)"
    assert stages[0][5] == "10 s" and stages[0][6] == "12 s"  # plan per task, elapsed
    assert stages[0][7] == "10 s" and stages[2][7] == "30 s" and stages[3][7] == "?"  # 3 tasks on 4 slots; 2; none
    w = _cells(page, "workers")
    base = WORKER_BASE_BYTES / 1e9
    # plan: the baseline and two of simulate's largest task (two threads busy); an idle worker: one
    assert w[0][4:7] == ["1.50", f"{base + 2 * 1.0:.2f}", "4.00"]
    assert w[1][4:7] == ["0.40", f"{base + 1.0:.2f}", "2.00"]
    assert "time left" in page and "and products: no plan" in page


def test_page_before_any_run_and_after_a_stop():
    b = RunBoard()
    page = render_page(page_state(b.snapshot(), []))
    assert "no mmflow run has started" in page and "no dask worker connected" in page
    b.begin_run("/r", "local", ["simulate"], [], 1)
    b.begin_stage("simulate", 2, 0)
    b.end_run("KeyboardInterrupt: <ctrl-c>")
    page = render_page(page_state(b.snapshot(), []))
    assert "stopped: KeyboardInterrupt: &lt;ctrl-c&gt;" in page and _cells(page, "stages")[0][2] == "stopped"
    b.end_run("InputError: refused", "/other")  # a run refused before it began: its refusal, not the last run
    s = b.snapshot()
    assert (s["run_dir"], s["error"], s["stages"]) == ("/other", "InputError: refused", [])


def test_durations_keep_a_small_runs_tenths():
    from mmflow.workflow.engine.dashboard.page import _duration

    assert [_duration(s) for s in (0.0286, 6.13, 0, 45, 300, 9000)] == ["0.03 s", "6.1 s", "0 s", "45 s", "5.0 min",
                                                                        "2.5 h"]


@pytest.mark.parametrize("bound, scheduler, link", [
    ("127.0.0.1", "tcp://10.1.2.3:8786", "http://127.0.0.1:8787/status"),  # SLURM: scheduler on the network
    ("0.0.0.0", "tcp://10.1.2.3:8786", "http://10.1.2.3:8787/status"),  # expose: any address; the scheduler's
    ("::1", "tcp://[::1]:8786", "http://[::1]:8787/status")])
def test_dashboard_link_is_where_the_dashboard_is_bound(bound, scheduler, link):
    from mmflow.workflow.engine.dashboard.page import dashboard_link

    cluster = SimpleNamespace(scheduler=SimpleNamespace(address=scheduler,
                                                        http_server=SimpleNamespace(address=bound, port=8787)))
    client = SimpleNamespace(dashboard_link="http://10.1.2.3:8787/status")  # dask's: the scheduler's host
    assert dashboard_link(cluster, client) == link
    assert dashboard_link(cluster, client, "mmflow") == link.replace("/status", "/mmflow")
    # a scheduler elsewhere (joined by address): dask's link is all there is
    assert dashboard_link(None, client, "mmflow") == "http://10.1.2.3:8787/mmflow"
