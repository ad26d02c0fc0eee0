"""A local cluster listens on loopback only, unless cluster.expose opts in to the network."""
import ipaddress
from urllib.parse import urlparse

import pytest

from mmflow.workflow.engine.cluster import dashboard_bind, memory_limit, open_cluster
from mmflow.workflow.config.schema import load_config


def _listening(client):
    """Host of the scheduler's address and the bound hosts of its dashboard's sockets."""
    sched = client.cluster.scheduler
    http = sched.http_server
    socks = [s.getsockname()[0] for s in getattr(http, "_sockets", {}).values()]
    return urlparse(client.scheduler.address).hostname, socks


@pytest.mark.parametrize("expose", [False, True])
def test_local_cluster_binds_loopback_unless_exposed(tmp_path, expose):
    cfg = load_config(None, ["cluster.n_workers=1", "cluster.dashboard_address=:0", f"cluster.expose={expose}",
                             f"run.directory={tmp_path}"])
    with open_cluster(cfg, log=lambda *a: None) as client:
        host, dash = _listening(client)
        workers = [urlparse(a).hostname for a in client.scheduler_info()["workers"]]
        assert dash, "the dashboard is listening"
        if not expose:
            assert ipaddress.ip_address(host).is_loopback
            assert all(ipaddress.ip_address(h).is_loopback for h in dash + workers)
        else:
            assert host == "0.0.0.0" or not ipaddress.ip_address(host).is_loopback
            assert "0.0.0.0" in dash


def test_dashboard_host_and_memory_limit_as_dask_takes_them():
    cfg = load_config(None, ["cluster.dashboard_address=:8790"])
    assert dashboard_bind(cfg.cluster) == "127.0.0.1:8790"
    cfg = load_config(None, ["cluster.dashboard_address=:8790", "cluster.expose=true"])
    assert dashboard_bind(cfg.cluster) == "0.0.0.0:8790"
    assert memory_limit("0.5") == 0.5 and memory_limit("4GiB") == "4GiB" and memory_limit("auto") == "auto"
