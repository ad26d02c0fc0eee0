"""``mmflow plan --cluster slurm``: jobs sized from the plan (issue 38, items 4 and 7).

Node sizes are given (no ``sinfo`` here) or read from a captured ``sinfo`` output; every plan is at a
fixed SGEMM peak so the figures do not move with the machine's load.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from mmflow.cli import main
from mmflow.errors import InputError
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.plan import jobs, nodes
from mmflow.workflow.plan.nodes import JOB_PROCESS_BYTES, MIB, Node, node_from_sinfo, node_size, parse_sinfo

ROOT = Path(__file__).resolve().parents[2]
PEAK = 197.0  # the constants' reference SGEMM peak (plan/costs.json)
GB = 1e9

#: ``sinfo -h -o '%c %m %D %P'`` of a cluster with two partitions, the default one of two node kinds
SINFO = """\
32 128000 12 compute*
64 256000+ 2 compute*
128 1024000 4 bigmem
"""


def _wf(name):
    return str(ROOT / "workflows" / name)


def _plan(cfg, node, **kw):
    return jobs.cluster_plan(cfg, node, peak_gflops=PEAK, **kw)


def _fits_its_worker(res):
    """Every stage's largest task within its worker's memory, its workers within a node."""
    node_mem = res["node"]["memory_gb"]
    for r in res["stages"]:
        assert r["task_gb"] <= r["worker_memory_gb"] * jobs.terminate_fraction(), r  # below dask's kill
        assert r["worker_cores"] * r["workers_per_node"] <= res["node"]["cores"]
        assert r["workers_per_node"] * r["worker_memory_gb"] <= node_mem + 1e-9


def test_sinfo_output_is_parsed():
    groups = parse_sinfo(SINFO)
    assert [(g["partition"], g["default"], g["cores"], g["nodes"]) for g in groups] == [
        ("compute", True, 32, 12), ("compute", True, 64, 2), ("bigmem", False, 128, 4)]
    assert groups[1]["memory_bytes"] == 256000 * 1024 ** 2  # '+': the smallest of the group
    node = node_from_sinfo(SINFO)  # the default partition, its commonest node kind, all its nodes
    assert (node.cores, node.memory_bytes, node.count, node.partition, node.source) == (
        32, 128000 * 1024 ** 2, 14, "compute", "sinfo")
    big = node_from_sinfo(SINFO, "bigmem")
    assert (big.cores, big.count) == (128, 4)
    # a given size wins over sinfo's; the rest still comes from it
    mixed = node_size(cores=16, sinfo_text=SINFO)
    assert (mixed.cores, mixed.memory_bytes, mixed.source) == (16, 128000 * 1024 ** 2, "sinfo and given")


def test_bad_sinfo_and_no_sinfo_are_refused_naming_the_options(monkeypatch):
    with pytest.raises(InputError, match="cannot read the line"):
        parse_sinfo("32 lots 4 compute\n")
    with pytest.raises(InputError, match="no partition 'gpu'"):
        node_from_sinfo(SINFO, "gpu")
    monkeypatch.setattr(nodes, "read_sinfo", lambda: None)  # no SLURM on this machine
    with pytest.raises(InputError, match="--node-cores 32 --node-memory 128GB"):
        node_size()
    assert node_size(32, "128GB").memory_bytes == 128e9  # given: sinfo is not asked


def test_job_shapes_of_the_demo_from_a_given_node_size():
    cfg = load_config(_wf("demo.yaml"))
    node = node_size(8, "32GB")
    # 29 whole GiB to a job (dask-jobqueue rounds --mem up to GiB), less the job's own process, by 8
    share, own = node.core_memory_bytes // MIB, JOB_PROCESS_BYTES // MIB
    assert 29 * 1024 - 8 <= share * 8 + own <= 29 * 1024 and node.job_memory_bytes == 29 * 2 ** 30
    res = _plan(cfg, node, nodes=2)
    assert res["settings"] == {} and res["nodes"] == 2
    _fits_its_worker(res)
    shapes = jobs.job_shapes(res)
    assert set(shapes) == {r["stage"] for r in res["stages"]}
    rows = {r["stage"]: r for r in res["stages"]}
    for stage, j in shapes.items():  # the demo's tasks are small: standard workers (a core, 4 GB)
        assert j["worker_cores"] == 1 and j["cores"] == j["processes"] and 1 <= j["count"] <= 2
        assert j["processes"] == min(8, -(-rows[stage]["tasks"] // j["count"]))  # whole nodes where filled
        assert j["memory"] == f"{j['processes'] * share + own}MiB"
        assert re.fullmatch(r"\d\d:[0-5]\d:00", j["walltime"])
    assert shapes["simulate"]["processes"] == 8 and shapes["simulate"]["memory"] == f"{8 * share + own}MiB"
    for n in (1, 5):  # a pure function of the plan and a node count: no more jobs than the tasks fill
        for stage, j in jobs.job_shapes(res, n).items():
            assert j["count"] == min(n, -(-rows[stage]["tasks"] // 8))


def test_the_paper_channel_gets_larger_workers_only_where_its_tasks_need_them():
    cfg = load_config(_wf("paper-scale.yaml"))
    node = Node(32, 128 * GB)
    res = _plan(cfg, node)
    _fits_its_worker(res)
    rows = {r["stage"]: r for r in res["stages"]}
    core = node.core_memory_bytes / GB
    frac = jobs.terminate_fraction()
    for r in rows.values():  # the fewest core-shares that hold the task below dask's kill threshold
        assert (r["worker_cores"] - 1) * core * frac < r["task_gb"] <= r["worker_cores"] * core * frac
    assert rows["transfer"]["worker_cores"] == 2  # 7.5 GB: two cores' share
    assert rows["mmodes"]["worker_cores"] == 1
    shapes = res["jobs"]
    assert rows["transfer"]["workers_per_node"] == 16 and rows["mmodes"]["workers_per_node"] == 32
    t = shapes["transfer"]  # its 8 tasks: one job of 8 workers of 2 cores, 8 GB each
    assert (t["count"], t["processes"], t["worker_cores"], t["cores"]) == (1, 8, 2, 16)
    assert t["memory"] == f"{(16 * node.core_memory_bytes + JOB_PROCESS_BYTES) // MIB}MiB"
    assert t["task_memory_bytes"] <= t["worker_memory_bytes"] * jobs.terminate_fraction()
    assert t["task_memory_bytes"] == pytest.approx(rows["transfer"]["task_gb"] * GB, abs=1)
    # the live stores' peak: the visibilities gone after mmodes, the partials (11.2 GB, packed) after normal
    assert res["nodes"] >= 1 and res["wall_s"] > 0 and 12 < res["store_gb"] < 20


@pytest.mark.parametrize("setting, value, node_bytes, stage", [
    ("mmode.baseline_chunk", 8192, 16 * GB, "mmodes"),
    ("transfer.m_block", 512, 16 * GB, "normal"),  # 22.9 GB: its Grams' packed triangles in complex128
    # the paper's channel at 128 baselines a chunk: an 8.5 GB transfer task, 6.65 GB at 32 (its Gram and group stay)
    ("transfer.baseline_chunk", 128, 7 * 2 ** 30, "transfer"),
])
def test_a_task_larger_than_a_node_is_split_by_replanning(setting, value, node_bytes, stage):
    cfg = load_config(_wf("paper-scale.yaml"), [f"{setting}={value}"])
    node = Node(16, node_bytes)
    node_gb = node.core_memory_bytes * node.cores / GB  # what its jobs may ask for
    before = {r["stage"]: r for r in jobs.stage_rows(cfg, jobs.geometry(cfg), node, 1, 50.0, jobs.load_costs(), 2)}
    assert before[stage]["task_gb"] > node_gb * jobs.terminate_fraction()  # as given it does not fit a node
    res = _plan(cfg, node)
    chosen = res["settings"][setting]
    assert chosen < value and list(res["settings"]) == [setting]
    _fits_its_worker(res)
    after = {r["stage"]: r for r in res["stages"]}[stage]
    assert after["task_gb"] <= node_gb * jobs.terminate_fraction()
    # the setting is the first halving that fits: one step larger does not
    larger = jobs.with_settings(cfg, {setting: chosen * 2})
    rows = {r["stage"]: r for r in jobs.stage_rows(larger, jobs.geometry(larger), node, 1, 50.0, jobs.load_costs(), 2)}
    assert rows[stage]["task_gb"] > node_gb * jobs.terminate_fraction()
    assert f"split to fit a node: {setting}={chosen}" in jobs.format_cluster_plan(res)


def test_the_352_antenna_array_fits_nodes_of_32_cores_and_128_gb(capsys):
    cfg = load_config(_wf("ovro-lwa-stage3.yaml"))
    ingest = jobs.layout_ingest(cfg)
    assert len(ingest.layout.names) == 352 and ingest.n_time == 6628
    res = _plan(cfg, Node(32, 128 * GB), ingest=ingest)
    _fits_its_worker(res)
    rows = {r["stage"]: r for r in res["stages"]}
    assert rows["transfer"]["task_gb"] > 30  # the lmax-2000 Gram (21.4 GB) and its group's m-modes: 35 GB
    assert rows["transfer"]["worker_cores"] > 1 and rows["calibrate"]["worker_cores"] == 1
    assert res["nodes"] >= 2 and res["store_gb"] > 150 and res["node_memory_gb"] <= 128
    # the CLI says the same, from the workflow file without its files
    assert main(["plan", _wf("ovro-lwa-stage3.yaml"), "--cluster", "slurm", "--node-cores", "32", "--node-memory",
                 "128GB", "--simulate-layout", "--peak", str(PEAK), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["nodes"] == res["nodes"] and out["jobs"]["transfer"] == res["jobs"]["transfer"]


def test_a_projection_for_8_and_64_nodes_is_json():
    cfg = load_config(_wf("ovro-lwa-stage3.yaml"))
    proj = jobs.array_projection((8, 64), peak_gflops=PEAK)  # what `mmflow bench cluster` states
    assert json.loads(json.dumps(proj))["array"] == {"workflow": "ovro-lwa-stage3.yaml", "antennas": 352,
                                                    "baselines": 62128, "integrations": 6628, "channels": 3,
                                                    "lmax": 2000}
    eight, many = proj["nodes"]["8"], proj["nodes"]["64"]
    assert many["wall_s"] < eight["wall_s"] and many["node_hours"] > 0
    res = jobs.cluster_plan(cfg, Node(32, 128 * GB), 64, peak_gflops=PEAK, ingest=jobs.layout_ingest(cfg))
    assert many["wall_s"] == pytest.approx(res["wall_s"])  # the projection is the plan on that many nodes
    assert many["wall_s"] >= max(r["per_task_s"] for r in res["stages"])  # no faster than its longest task
    assert eight["jobs"]["transfer"]["count"] == 8  # 24 tasks, three a node
    assert many["jobs"]["transfer"]["count"] == 8  # 24 tasks of 35 GB, three a node
    assert many["jobs"]["solve"]["count"] == 12  # 378 tasks, 32 a node
    assert proj["store_gb"] > 150 and 0 < eight["node_memory_gb"] <= 128


def test_a_task_no_split_fits_is_refused_naming_the_limit():
    cfg = load_config(_wf("ovro-lwa-stage3.yaml"))
    with pytest.raises(InputError) as err:
        _plan(cfg, Node(32, 16 * GB), ingest=jobs.layout_ingest(cfg))
    msg = str(err.value)
    assert "stage transfer" in msg and "even with transfer.baseline_chunk=1" in msg
    # 14 GiB to a job, less its own process, in whole MiB a core (438 x 32), 95 % of it
    assert "the 13.96 GB a worker may hold on a node of 16.00 GB" in msg
    assert "mmode.lmax" in msg and "--node-memory" in msg


def test_the_plan_without_cluster_is_unchanged(capsys):
    assert main(["plan", _wf("demo.yaml"), "--peak", str(PEAK)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split() == ["stage", "tasks", "task", "GB", "store", "GB", "time"]
    assert "job" not in out and "nodes" not in out


def test_the_cli_reads_the_nodes_from_sinfo_or_says_what_to_give(monkeypatch, capsys):
    args = ["plan", _wf("demo.yaml"), "--cluster", "slurm", "--node-peak", "800", "--json"]
    monkeypatch.setattr(nodes, "read_sinfo", lambda: None)
    assert main(args) == 2
    assert "--node-cores 32 --node-memory 128GB" in capsys.readouterr().err
    monkeypatch.setattr(nodes, "read_sinfo", lambda: SINFO)  # as `sinfo -h -o '%c %m %D %P'` prints it
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["node"] == {"cores": 32, "memory_gb": 128000 * 1024 ** 2 / GB, "partition": "compute",
                           "source": "sinfo", "available": 14,
                           "core_memory_bytes": 3990 * MIB}  # 125 GiB less the job's own process, by 32
    assert 1 <= out["nodes"] <= 14  # no more nodes than the partition has
    assert main(args + ["--partition", "bigmem"]) == 0
    assert json.loads(capsys.readouterr().out)["node"]["cores"] == 128


def test_an_ingesting_workflow_without_its_files_points_to_simulate_layout(capsys):
    assert main(["plan", _wf("ovro-lwa-stage3.yaml"), "--cluster", "slurm", "--node-cores", "32",
                 "--node-memory", "128GB", "--node-peak", "3150"]) == 2
    err = capsys.readouterr().err
    assert "input.path" in err and "--simulate-layout" in err


def test_the_workflows_own_jobqueue_is_checked_against_the_tasks():
    cfg = load_config(_wf("hpc-slurm.yaml"))  # 64GB over 2 processes: workers of 32 GB
    res = _plan(cfg, Node(16, 64 * GB))
    assert res["configured_worker_gb"] == pytest.approx(32.0) and res["too_large_for_configured"] == []
    assert "enough for every stage's task" in jobs.format_cluster_plan(res)
    cfg = load_config(_wf("hpc-slurm.yaml"), ["cluster.jobqueue.processes=40", "cluster.jobqueue.memory=16GB"])
    small = _plan(cfg, Node(16, 64 * GB))  # workers of 0.4 GB: below some of the demo's tasks
    rows = {r["stage"]: r for r in small["stages"]}
    big = [s for s, r in rows.items() if r["task_gb"] > 0.4 * jobs.terminate_fraction()]
    assert small["too_large_for_configured"] == big and 0 < len(big) < len(rows)
    assert f"too small for {', '.join(big)}" in jobs.format_cluster_plan(small)


def test_every_job_dask_jobqueue_submits_fits_the_nodes_memory():
    """dask-jobqueue asks SLURM for a job's memory rounded up to whole GiB (``#SBATCH --mem=126G``): a
    job sized to a node's 128500 MB (not whole GiB) must still ask for no more than the node has."""
    from dask.utils import parse_bytes
    from dask_jobqueue.slurm import slurm_format_bytes_ceil

    node = node_from_sinfo("32 128500 4 compute*\n")
    res = _plan(load_config(_wf("paper-scale.yaml")), node)
    for stage, j in res["jobs"].items():
        mem = slurm_format_bytes_ceil(parse_bytes(j["memory"]))  # what the job script says
        assert mem.endswith("G") and int(mem[:-1]) * 1024 <= 128500, (stage, j["memory"], mem)
        # its workers' shares and its own process; dask's limit for a worker, memory / processes, holds its share
        assert parse_bytes(j["memory"]) - JOB_PROCESS_BYTES == j["processes"] * j["worker_memory_bytes"]
