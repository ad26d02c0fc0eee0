"""``mmflow bench cluster --quick`` on the session's namespaced SLURM cluster (tests/cluster/conftest.py):
the JSON's structure and its invariants (maps bit-identical to the local run, nothing but task results
between the nodes, overheads finite numbers), never its times."""
import json
import math

import pytest

from mmflow.bench import cluster as bench_cluster
from mmflow.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.cluster]


def test_bench_cluster_quick_on_one_two_and_three_nodes(slurm_session, tmp_path):
    res = bench_cluster.run("cluster", quick=True, slurm=slurm_session, directory=tmp_path)
    print(json.dumps(res))  # JSON-ready (shown with -s)
    assert res["ran"] is True and res["sgemm_gflops"] > 0
    assert res["workflow"]["settings"] == "the test suite's small demo"
    ref = res["reference"]
    assert ref["tasks"] > 0 and ref["arrays"] > 0
    assert [r["nodes"] for r in res["runs"]] == [1, 2, 3]
    for r in res["runs"]:
        assert r["identical"] is True, r
        assert r["workers"] == r["nodes"] == len(r["hosts"]), r  # one exclusive job per node
        assert set(r["hosts"]) <= set(slurm_session.nodes)
        assert r["tasks"] == ref["tasks"] and r["records"] >= r["tasks"], r
        for key in ("overhead_fraction", "overhead_per_task_s", "wrapper_fraction", "wall_s", "task_s"):
            assert isinstance(r[key], float) and math.isfinite(r[key]), (key, r)
        assert r["overhead_fraction"] > -1 and r["dask_compute_s"] > 0
        assert abs(r["store_bytes"] - ref["store_bytes"]) < 0.01 * ref["store_bytes"], r  # the stores' metadata aside
        # tasks write the shared stores; nothing of them goes from node to node, and only small results to the driver
        assert r["bytes_between_workers"] <= 1e-3 * r["store_bytes"], r
        assert r["dependency_transfers"] == 0, r
        assert r["bytes_to_driver"] < 0.05 * r["store_bytes"], r
    proj = res["projection"]
    assert set(proj["nodes"]) == {"8", "64"} and proj["array"]["antennas"] == 352
    over = res["overhead_at_array_task_sizes"]
    assert over["array_tasks"] > 0 and math.isfinite(over["fraction"]) and over["fraction"] >= 0
    assert set(over["stage_barriers_fraction_of_wall"]) == {"8", "64"}
    assert all(math.isfinite(f) and f >= 0 for f in over["stage_barriers_fraction_of_wall"].values())


def test_bench_cluster_without_namespaces_says_why_and_exits_0(monkeypatch, capsys):
    monkeypatch.setattr(bench_cluster, "unavailable", lambda: "needs root (network namespaces, a bridge, slurmd)")
    assert main(["bench", "cluster", "--quick"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["ran"] is False and "needs root" in res["why"]
