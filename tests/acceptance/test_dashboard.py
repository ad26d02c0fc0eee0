"""The dashboard a run prints answers, and mmflow's page in it shows the run (headless Chromium).

Every server here listens on loopback addresses only.
"""
import http.client
import json
import re
import threading
import time
import urllib.error
import urllib.request

import pytest

from mmflow.workflow.engine.cluster import jobqueue_cluster, open_cluster
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.dashboard.page import dashboard_link, serve_page
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.engine.runner import run_workflow

from tests.headless_chromium import Chromium, dump_dom, install_chromium
from tests.workflow_helpers import small_config


def _get(url):
    with urllib.request.urlopen(url, timeout=30) as r:
        return r.status, r.read().decode()


def _printed_links(lines):
    """The dashboard's and mmflow's page's addresses from the line the cluster's start prints."""
    line = next(ln for ln in lines if ln.startswith("dask dashboard: "))
    m = re.fullmatch(r"dask dashboard: (\S+) \(mmflow's page: (\S+)\)", line)
    assert m, line
    return m.group(1), m.group(2)


def test_the_printed_links_of_a_local_cluster_answer(tmp_path):
    cfg = small_config(tmp_path / "r", "cluster.kind=local", "cluster.n_workers=1", "cluster.dashboard_address=:0")
    lines = []
    with open_cluster(cfg, log=lines.append) as client:
        client.scheduler_info()  # starts the cluster, which prints its links
        status, page = _printed_links(lines)
        assert status.startswith("http://127.0.0.1:") and status.endswith("/status")
        code, body = _get(status)
        assert code == 200 and "bokeh" in body.lower() and "Dask needs bokeh" not in body  # dask's own dashboard
        code, body = _get(page)
        assert code == 200 and "<h1>mmflow run</h1>" in body


def test_a_batch_clusters_link_is_the_address_its_dashboard_listens_on(tmp_path):
    """A SLURM cluster's scheduler listens on the cluster network, its dashboard elsewhere (loopback):
    dask's link puts the scheduler's host before the dashboard's port and is refused; the printed link
    is the dashboard's bound address. Here the scheduler on 127.0.0.1, the dashboard on 127.0.0.2
    stand for the two (no job is submitted)."""
    cfg = load_config(None, ["cluster.kind=slurm", "cluster.dashboard_address=127.0.0.2:0",
                             "cluster.jobqueue={cores: 1, memory: 1GB, scheduler_options: {host: 127.0.0.1}}",
                             f"run.directory={tmp_path}"])
    serve_page()
    cluster = jobqueue_cluster(cfg, "slurm")
    try:
        link, page = dashboard_link(cluster, None), dashboard_link(cluster, None, "mmflow")
        assert link.startswith("http://127.0.0.2:") and page == link[: -len("status")] + "mmflow"
        assert _get(link)[0] == 200 and "<h1>mmflow run</h1>" in _get(page)[1]
        # dask's own link: the scheduler's host with the dashboard's port, where no dashboard listens (nothing at
        # all, or, when the two random ports happen to be equal, the scheduler's own comm, which speaks no HTTP)
        with pytest.raises((urllib.error.URLError, http.client.HTTPException, ConnectionError)):
            _get(cluster.dashboard_link)
    finally:
        cluster.close()


@pytest.fixture(scope="module")
def chromium():
    exe, why = install_chromium()
    if exe is None:
        pytest.skip(why)
    return exe


def _table(dom, table_id):
    """Rows of cells (text) of the table ``table_id`` in serialized HTML (the header row left out)."""
    table = re.search(rf'<table id="{table_id}">(.*?)</table>', dom, re.S)
    assert table, f"no table {table_id}"
    rows = [re.findall(r"<td[^>]*>(.*?)</td>", row, re.S) for row in re.findall(r"<tr[^>]*>(.*?)</tr>", table.group(1),
                                                                               re.S)]
    return [[re.sub(r"<[^>]+>", "", c).strip() for c in r] for r in rows if r]


def _cell(dom, cell_id):
    m = re.search(rf'<td class="l" id="{cell_id}">(.*?)</td>', dom, re.S)
    return re.sub(r"<[^>]+>", "", m.group(1)).strip() if m else None


def test_the_mmflow_page_renders_the_run_in_headless_chromium(tmp_path, chromium):
    run_dir = tmp_path / "run"
    cfg = small_config(run_dir, "cluster.kind=local", "cluster.n_workers=1", "cluster.dashboard_address=:0")
    stages = [st.name for st in PIPELINE if st.enabled(cfg) and st.task is not None]
    lines, result = [], {}
    with open_cluster(cfg, log=lines.append) as client:
        client.scheduler_info()
        _, page = _printed_links(lines)

        def run():
            try:
                result["summaries"] = run_workflow(cfg, client, progress=False, log=lambda m: None)
            except BaseException as exc:  # noqa: BLE001 - reported below
                result["error"] = exc

        driver = threading.Thread(target=run)
        driver.start()
        during = None
        while driver.is_alive():  # the page while the run goes on: once its first task finished
            state = json.loads(_get(page + ".json")[1])
            if state["ended"] is None and any(r["done"] for r in state["stages"]):
                during = dump_dom(chromium, page)
                break
            time.sleep(0.2)
        driver.join()
        assert "error" not in result, result.get("error")
        after = dump_dom(chromium, page)
        with Chromium(chromium) as browser:
            browser.open(page)
            browser.screenshot(tmp_path / "mmflow_page.png")
            heading = browser.evaluate("document.querySelector('h1').textContent")
            n_rows = browser.evaluate("document.querySelectorAll('#stages tr').length")
            errors = [e for e in browser.errors() if "favicon" not in e]
    (tmp_path / "mmflow_page_during.html").write_text(during or "")
    (tmp_path / "mmflow_page_after.html").write_text(after)
    assert heading == "mmflow run" and n_rows == len(stages) + 1 and errors == []

    # during the run: the stages in pipeline order, real counts, at least one task done, time left from the plan
    assert during is not None, "the run ended before its first task was seen"
    rows = _table(during, "stages")
    assert [r[1] for r in rows] == stages
    counts = [tuple(int(x) for x in re.match(r"(\d+)/(\d+)", r[3]).groups()) for r in rows]
    assert sum(d for d, _ in counts) > 0 and all(0 <= d <= t for d, t in counts)
    assert re.fullmatch(r"\d+(\.\d+)? (s|min|h)", rows[-1][7])  # the last stage's time left, from its plan
    assert _cell(during, "status").startswith(("running for", "finished in"))

    # after: every stage done with the run's own task counts, nothing left, the worker against its plan
    rows = _table(after, "stages")
    summaries = result["summaries"]
    assert [r[1] for r in rows] == stages and all(r[2] == "done" for r in rows)
    assert [r[3] for r in rows] == [f"{summaries[s]['tasks']}/{summaries[s]['tasks']}" for s in stages]
    assert all(r[7] == "0 s" for r in rows) and all(float(r[8]) > 0.3 for r in rows)  # plan GB: baseline and more
    assert _cell(after, "run-dir") == str(run_dir) and _cell(after, "cluster") == "local"
    assert _cell(after, "time-left") == "0 s" and _cell(after, "status").startswith("finished in")
    (worker,) = _table(after, "workers")
    memory, limit = float(worker[4]), float(worker[6])
    assert worker[1].startswith("tcp://127.0.0.1:") and 0.05 < memory < limit


def test_a_fresh_install_and_the_image_have_the_dashboard():
    """bokeh (dask's dashboard) is one of mmflow's dependencies; the docker image installs the ``ms`` extra
    (python-casacore, MeasurementSet input) as well."""
    import tomllib

    from tests.workflow_helpers import ROOT

    with open(f"{ROOT}/pyproject.toml", "rb") as fh:
        project = tomllib.load(fh)["project"]
    assert any(d.replace(" ", "").startswith("bokeh>=3.1") for d in project["dependencies"])
    assert any(d.startswith("python-casacore") for d in project["optional-dependencies"]["ms"])
    with open(f"{ROOT}/docker/Dockerfile") as fh:
        assert "RUN pip install .'[ms]'" in fh.read()
