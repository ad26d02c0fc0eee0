"""Worker jobs sized per stage from the plan, without a batch system (tests/cluster runs them on a real
SLURM): stages grouped by worker into pools, and the switch between pools on a stand-in cluster."""
from pathlib import Path

import pytest

from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.batch import lifetime_args
from mmflow.workflow.engine.pools import TASK_SLOT, StagePools, describe, job_prologue, plan_pools, with_task_slot
from mmflow.workflow.plan import jobs
from mmflow.workflow.plan.nodes import JOB_PROCESS_BYTES, MIB, Node
from tests.workflow_helpers import small_config

ROOT = Path(__file__).resolve().parents[2]
GB = 1e9


@pytest.fixture(scope="module")
def paper_plan():
    return jobs.cluster_plan(load_config(str(ROOT / "workflows" / "paper-scale.yaml")), Node(32, 128 * GB),
                             peak_gflops=197.0)


def test_stages_of_one_worker_share_a_pool_and_larger_workers_serve_only_those_that_need_them(paper_plan):
    pools = jobs.worker_pools(paper_plan)
    shapes, rows = paper_plan["jobs"], {r["stage"]: r for r in paper_plan["stages"]}
    assert set(pools) == set(shapes)
    for stage, pool in pools.items():
        assert pool["worker_cores"] == rows[stage]["worker_cores"] and stage in pool["stages"]
        assert all(pools[s] is pool for s in pool["stages"])  # one dict: the stages share its jobs
        mine = [shapes[s] for s in pool["stages"]]
        assert pool["count"] == max(j["count"] for j in mine) and pool["processes"] == max(j["processes"] for j in mine)
        assert pool["task_memory_bytes"] <= pool["worker_memory_bytes"] * jobs.terminate_fraction()
        assert pool["cores"] == pool["processes"] * pool["worker_cores"] <= 32  # a job fits a node
        share = Node(32, 128 * GB).core_memory_bytes  # a core's, beside the job's own process
        assert pool["memory"] == f"{(pool['cores'] * share + JOB_PROCESS_BYTES) // MIB}MiB"
    assert pools["transfer"]["worker_cores"] == 2 and pools["transfer"]["stages"] == ["transfer"]
    assert pools["mmodes"] is pools["normal"] and pools["mmodes"]["worker_cores"] == 1


class _Cluster:
    """A dask-jobqueue cluster's scaling as StagePools uses it (SpecCluster's naming and scale)."""

    job_cls = "job"

    def __init__(self):
        self.worker_spec, self.new_spec, self._i, self._job_kwargs, self.scaled = {}, None, 0, {}, []

    def scale(self, jobs):
        self.scaled.append(jobs)
        while len(self.worker_spec) < jobs:
            while f"job-{self._i}" in self.worker_spec:
                self._i += 1
            self.worker_spec[f"job-{self._i}"] = self.new_spec


class _Client:
    def __init__(self, cluster):
        self.cluster, self.retired = cluster, []

    def scheduler_info(self):
        return {"workers": {f"tcp://{n}{s}": {"name": f"{n}{s}"} for n, spec in self.cluster.worker_spec.items()
                            for s in spec.get("group", [""])}}

    def retire_workers(self, names, close_workers):
        self.retired.append(sorted(names))


def test_a_stage_of_larger_workers_retires_the_running_jobs_one_of_smaller_keeps_them(paper_plan):
    pools, cluster, said = jobs.worker_pools(paper_plan), _Cluster(), []
    client = _Client(cluster)
    sp = StagePools(cluster, pools, {"queue": "compute", "walltime": None, "worker_extra_args": ["--nthreads", "1"]},
                    None, said.append)
    assert sp.use("mmodes", client) is pools["mmodes"]
    one = pools["mmodes"]
    assert cluster.scaled == [one["count"]] and client.retired == []
    opts = cluster.new_spec["options"]
    assert (opts["cores"], opts["memory"], opts["processes"]) == (one["cores"], one["memory"], one["processes"])
    assert opts["queue"] == "compute" and cluster.new_spec["group"] == [f"-{i}" for i in range(one["processes"])]
    # a worker's core shares: the resource each task of a stage run on pools asks its pool's worker cores of
    assert opts["worker_extra_args"] == ["--nthreads", "1", *lifetime_args(one["walltime"]), "--resources",
                                         f"{TASK_SLOT}=1"]
    assert with_task_slot(["--resources", "GPU=1"], 2) == ["--resources", f"GPU=1 {TASK_SLOT}=2"]
    assert opts["job_script_prologue"] == job_prologue(one["processes"])
    assert opts["job_script_prologue"][0] == f"export MMFLOW_WORKERS_PER_HOST={one['processes']}"
    assert said[-1].startswith(f"stage mmodes: {describe(one)}")
    first = set(cluster.worker_spec)
    sp.use("transfer", client)  # 2-core workers: the 1-core jobs retired, new names
    two = pools["transfer"]
    assert client.retired == [sorted(f"{n}-{i}" for n in first for i in range(one["processes"]))]
    assert not set(cluster.worker_spec) & first and len(cluster.worker_spec) == two["count"]
    assert cluster.new_spec["options"]["cores"] == two["cores"] and cluster._job_kwargs["processes"] == two["processes"]
    assert "the running jobs retired" in said[-1]
    assert cluster.new_spec["options"]["worker_extra_args"][-1] == f"{TASK_SLOT}=2"  # two core shares a worker
    kept = set(cluster.worker_spec)
    # back to 1-core workers: the 2-core jobs kept, two of its tasks at once a worker, and as many more of them
    # as the 1-core pool's cores need
    assert sp.use("normal", client) is pools["normal"]
    small = pools["normal"]
    more = -(-small["count"] * small["cores"] // two["cores"]) - two["count"]
    assert more > 0 and kept <= set(cluster.worker_spec) and len(client.retired) == 1
    assert cluster.scaled[-1] == two["count"] + more and cluster.new_spec["options"]["cores"] == two["cores"]
    assert said[-1].startswith(f"stage normal: the running jobs kept ({two['count']} of {two['cores']} cores, "
                               f"{more} more submitted): a worker runs 2 of its tasks at once")
    n_said, n_scaled = len(said), len(cluster.scaled)
    sp.use("solve", client)  # the pool the kept jobs serve: nothing changes, nothing said
    sp.use("transfer", client)  # the running jobs' own pool
    assert len(said) == n_said and len(cluster.scaled) == n_scaled and len(client.retired) == 1


def test_jobs_are_sized_per_stage_only_when_the_workflow_gives_no_shape_and_sinfo_answers(tmp_path, monkeypatch):
    import dask_jobqueue  # noqa: F401  (loads dask's jobqueue.yaml defaults, as jobqueue_cluster does)

    from mmflow.workflow.plan import nodes

    cfg = small_config(tmp_path / "run", "cluster.kind=slurm")
    monkeypatch.setattr(nodes, "read_sinfo", lambda: "2 1500 3 debug*\n")
    said = []
    pools = plan_pools(cfg, "slurm", {}, said.append)
    assert pools is not None and set(pools) == {"simulate", "mmodes", "transfer", "normal", "solve", "products"}
    # 1 GiB to a job, less its own process, by 2 cores: workers of one or two 364 MiB shares
    assert all(p["worker_memory_bytes"] == p["worker_cores"] * 364 * MIB for p in pools.values())
    assert "sized per stage from the plan" in said[0]
    assert plan_pools(cfg, "slurm", {"cores": 2}, said.append) is None  # the workflow's shape wins
    assert plan_pools(cfg, "pbs", {}, said.append) is None  # no sinfo: one shape, as before
    monkeypatch.setattr(nodes, "read_sinfo", lambda: None)
    assert plan_pools(cfg, "slurm", {}, said.append) is None


def test_a_run_on_nodes_too_small_for_a_task_applies_the_plans_split(tmp_path, monkeypatch):
    """Issue 38, item 4: on a partition whose nodes (sinfo: 16 cores, 16 GB) hold the paper channel's normal
    task only split, ``mmflow run --cluster slurm`` runs with the plan's split (``transfer.m_block`` halved
    from 512 to 256), says so, and every stage's task then fits its worker; without
    ``--cluster`` (or with a job shape of the workflow's own) nothing changes."""
    from mmflow.cli import _run_config, build_parser
    from mmflow.workflow.plan import nodes

    monkeypatch.setattr(nodes, "read_sinfo", lambda: "16 16000 13 debug*\n")
    argv = ["run", "workflows/paper-scale.yaml", "transfer.m_block=512", f"run.directory={tmp_path / 'run'}"]
    said = []
    cfg = _run_config(build_parser().parse_args([*argv, "--cluster", "slurm"]), said.append)
    node = nodes.node_size(sinfo_text=nodes.read_sinfo())
    as_given = jobs.cluster_plan(load_config("workflows/paper-scale.yaml", ["transfer.m_block=512"]), node, None)
    assert as_given["settings"] == {"transfer.m_block": 256}  # the plan's split
    assert cfg.transfer.m_block == 256 and cfg.cluster.kind == "slurm"
    assert said and "the run splits it with transfer.m_block=256" in said[0], said
    res = jobs.cluster_plan(cfg, node, None)
    assert res["settings"] == {}
    for row in res["stages"]:  # every task within its worker's memory, below dask's kill threshold
        assert row["task_gb"] <= row["worker_memory_gb"] * jobs.terminate_fraction(), row
    assert plan_pools(cfg, "slurm", {}, said.append) is not None  # the run's pools: no refusal
    assert _run_config(build_parser().parse_args(argv), said.append).transfer.m_block == 512
    shaped = [*argv, "cluster.jobqueue={cores: 16, memory: 15GB}", "--cluster", "slurm"]
    assert _run_config(build_parser().parse_args(shaped), said.append).transfer.m_block == 512


def test_a_task_is_checked_against_its_share_of_a_worker_that_runs_several_at_once():
    """Before any work a task is held to a worker's memory limit over the tasks the worker runs at once: its
    threads, or one where it has the pools' task slot (mmflow.workflow.engine.runner._worker_limit_gb)."""
    from mmflow.workflow.engine.runner import _worker_limit_gb

    class Client:
        def __init__(self, workers):
            self.workers = workers

        def scheduler_info(self):
            return {"workers": self.workers}

    threaded = {"memory_limit": 4e9, "nthreads": 4}
    slotted = {"memory_limit": 3e9, "nthreads": 2, "resources": {TASK_SLOT: 1}}
    assert _worker_limit_gb(Client({"a": threaded})) == 1.0
    assert _worker_limit_gb(Client({"b": slotted})) == 3.0
    assert _worker_limit_gb(Client({"a": threaded, "b": slotted})) == 1.0
    assert _worker_limit_gb(Client({})) is None
