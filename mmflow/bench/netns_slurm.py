"""A real SLURM cluster on one machine: a controller and compute nodes in network namespaces.

Each compute node is its own network namespace (``ip netns``) and hostname (a UTS namespace), joined
to the host by a veth pair on a bridge the cluster makes. Addresses exist only on that bridge and
inside those namespaces (one private /24, no default route in a namespace): a worker on a node
reaches the driver's scheduler over the bridge, never over loopback, and no traffic leaves the
machine. The run directory is shared (one filesystem), as on a cluster with a shared filesystem.

* ``munged`` runs on the host with a key and socket of its own (a unix socket: every namespace
  reaches it through the filesystem);
* ``slurmctld`` runs in a network namespace (and hostname) of its own on the same bridge, so that
  it listens on no interface of the host;
* each ``slurmd`` is started by ``nsenter --net=/run/netns/NODE unshare --uts``: ``ip netns exec``
  remounts /sys, and slurmd 22.05 then exits with "No filesystem mounted on /sys/fs/cgroup".

Everything is stopped by PID and the namespaces, veths and bridge are deleted by :meth:`stop`
(also after a failed start). Needs root, ``ip``, ``nsenter``/``unshare``, ``slurm-wlm`` and
``munge`` (:func:`ensure_packages` installs the last two with apt-get where it can).
"""
from __future__ import annotations

import ipaddress
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

#: Debian packages the cluster needs, and a program each provides
PACKAGES = {"slurm-wlm": "slurmctld", "munge": "munged", "iproute2": "ip"}
#: the controller's hostname (in its UTS namespace)
CONTROLLER = "mmctl"
#: the private range the cluster's /24 is taken from (the first one no route or address uses)
SUBNETS = ipaddress.ip_network("10.213.0.0/16")


def _run(*args, check=True, **kw):
    return subprocess.run(list(args), check=check, capture_output=True, text=True, **kw)


def unavailable():
    """Why a namespaced SLURM cluster cannot start here (a sentence), or None when it can."""
    if os.geteuid() != 0:
        return "needs root (network namespaces, a bridge, slurmd)"
    for prog in ("nsenter", "unshare"):
        if shutil.which(prog) is None:
            return f"needs {prog} (util-linux)"
    missing = [pkg for pkg, prog in PACKAGES.items() if shutil.which(prog) is None]
    if missing:
        why = ensure_packages(missing)
        if why:
            return why
    probe = f"mmprobe{os.getpid() % 100000}"
    try:
        _run("ip", "netns", "add", probe)
    except subprocess.CalledProcessError as e:
        return f"cannot make a network namespace ({e.stderr.strip()})"
    _run("ip", "netns", "del", probe, check=False)
    return None


def ensure_packages(packages):
    """Install Debian ``packages`` with apt-get (root, a clean CI machine); a sentence on failure."""
    if shutil.which("apt-get") is None:
        return f"needs {', '.join(packages)} and there is no apt-get to install them"
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    for cmd in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", *packages]):
        r = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if r.returncode:
            return f"`{' '.join(cmd)}` failed: {(r.stderr or r.stdout).strip()[-300:]}"
    return None


def _free_subnet():
    """The first /24 of :data:`SUBNETS` that no address or route of this machine overlaps."""
    used = []
    for line in _run("ip", "-4", "-o", "addr").stdout.splitlines() + _run("ip", "-4", "route").stdout.splitlines():
        for word in line.split():
            try:
                used.append(ipaddress.ip_network(word, strict=False))
            except ValueError:
                pass
    start = os.getpid() % 200  # concurrent clusters on one machine start their search apart
    nets = list(SUBNETS.subnets(new_prefix=24))
    for net in nets[start:] + nets[:start]:
        if not any(net.overlaps(u) for u in used if u.prefixlen > 0):
            return net
    raise RuntimeError(f"no free /24 in {SUBNETS}")


class NamespacedSlurm:
    """A SLURM controller and ``n_nodes`` compute nodes of ``cpus`` CPUs and ``memory_mb`` MB each.

    Parameters
    ----------
    root : pathlib.Path
        An empty directory for the configuration, state, spool and log files.
    n_nodes : int
        Compute nodes, each in a network namespace of its own.
    cpus, memory_mb : int
        Each node's CPUs and RealMemory as slurm.conf declares them.
    tag : str, optional
        Prefix of the namespaces, veths and bridge (at most 7 characters: interface names); default
        ``mm<pid>``. Two clusters in one process need tags of their own.
    """

    def __init__(self, root, n_nodes=3, cpus=2, memory_mb=3000, tag=None):
        self.root = Path(root)
        self.tag = tag or f"mm{os.getpid() % 100000}"
        self.n_nodes, self.cpus, self.memory_mb = n_nodes, cpus, memory_mb
        self.nodes = [f"node{i + 1}" for i in range(n_nodes)]
        self.procs = {}  # name -> Popen (munged, slurmctld, slurmd of each node)
        self.netns, self.links = [], []
        self.subnet = None
        self.bridge = f"{self.tag}br"
        self.conf = self.root / "slurm.conf"

    # -- names ----------------------------------------------------------------------------
    @property
    def host_address(self):
        """The bridge's address: where a driver on the host side listens for the workers."""
        return str(self.subnet[1])

    @property
    def ctl_address(self):
        """The controller's address (in its own namespace)."""
        return str(self.subnet[2])

    @property
    def ctl_ns(self):
        return f"{self.tag}ctl"

    def address(self, node):
        return str(self.subnet[10 + self.nodes.index(node)])

    def ns(self, node):
        return f"{self.tag}{node}"

    @property
    def env(self):
        """Environment for SLURM's commands (sbatch, squeue, ...) to reach this cluster."""
        return {"SLURM_CONF": str(self.conf)}

    # -- start / stop ---------------------------------------------------------------------
    def start(self, timeout=60):
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            self._network()
            self._munge()
            self._write_conf()
            self._spawn_in("slurmctld", self.ctl_ns, CONTROLLER, f"slurmctld -D -i -f {self.conf}")
            for node in self.nodes:
                self.start_node(node)
            self.wait_idle(self.nodes, timeout)
        except BaseException:
            self.stop()
            raise
        return self

    def _network(self):
        self.subnet = _free_subnet()
        _run("ip", "link", "add", self.bridge, "type", "bridge")
        self.links.append(self.bridge)
        _run("ip", "addr", "add", f"{self.host_address}/24", "dev", self.bridge)
        _run("ip", "link", "set", self.bridge, "up")
        self._namespace(self.ctl_ns, "x", self.ctl_address)
        for i, node in enumerate(self.nodes):
            self._namespace(self.ns(node), str(i), self.address(node))

    def _namespace(self, ns, suffix, address):
        """A network namespace joined to the bridge by a veth pair, ``address`` on its end."""
        host_end, ns_end = f"{self.tag}h{suffix}", f"{self.tag}c{suffix}"
        _run("ip", "netns", "add", ns)
        self.netns.append(ns)
        _run("ip", "link", "add", host_end, "type", "veth", "peer", "name", ns_end)
        self.links.append(host_end)
        _run("ip", "link", "set", host_end, "master", self.bridge)
        _run("ip", "link", "set", host_end, "up")
        _run("ip", "link", "set", ns_end, "netns", ns)
        _run("ip", "-n", ns, "addr", "add", f"{address}/24", "dev", ns_end)
        _run("ip", "-n", ns, "link", "set", ns_end, "up")
        _run("ip", "-n", ns, "link", "set", "lo", "up")  # no default route: the bridge's /24 only

    def _munge(self):
        d = self.root / "munge"
        d.mkdir(mode=0o700)
        key = d / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        self.munge_socket = d / "munge.sock"
        self._spawn("munged", ["munged", "-F", "--force", f"--socket={self.munge_socket}", f"--key-file={key}",
                               f"--pid-file={d / 'munged.pid'}", f"--log-file={d / 'munged.log'}",
                               f"--seed-file={d / 'munged.seed'}", "--num-threads=2"])
        deadline = time.time() + 10
        while not self.munge_socket.exists():
            if time.time() > deadline or self.procs["munged"].poll() is not None:
                raise RuntimeError(f"munged did not start: {self._tail(d / 'munged.log')}")
            time.sleep(0.05)

    def _write_conf(self):
        state = self.root / "state"
        state.mkdir()
        for node in self.nodes:
            (self.root / node / "spool").mkdir(parents=True)
        r = self.root
        lines = [
            "ClusterName=mmflowtest",
            f"SlurmctldHost={CONTROLLER}({self.ctl_address})",  # every daemon its own namespace: default ports
            "SlurmctldPort=6817", "SlurmdPort=6818",
            "SlurmUser=root", "SlurmdUser=root",
            f"AuthInfo=socket={self.munge_socket}",
            f"StateSaveLocation={state}", f"SlurmctldPidFile={r / 'slurmctld.pid'}",
            f"SlurmctldLogFile={r / 'slurmctld.log'}",
            f"SlurmdSpoolDir={r}/%n/spool", f"SlurmdPidFile={r}/%n/slurmd.pid", f"SlurmdLogFile={r}/%n/slurmd.log",
            "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none", "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none", "SwitchType=switch/none", "MpiDefault=none",
            "SelectType=select/cons_tres", "SelectTypeParameters=CR_Core_Memory",
            "SlurmdParameters=config_overrides", "ReturnToService=2",
            "SlurmctldTimeout=10", "SlurmdTimeout=10", "MessageTimeout=5", "KillWait=2", "MinJobAge=5",
            "InactiveLimit=0", "OverTimeLimit=0", "SchedulerParameters=sched_min_interval=200000",
            "SlurmctldDebug=info", "SlurmdDebug=info",
        ]
        for node in self.nodes:
            lines.append(f"NodeName={node} NodeAddr={self.address(node)} CPUs={self.cpus} "
                         f"RealMemory={self.memory_mb} State=UNKNOWN")
        lines.append(f"PartitionName=debug Nodes={','.join(self.nodes)} Default=YES MaxTime=INFINITE State=UP")
        self.conf.write_text("\n".join(lines) + "\n")

    def start_node(self, node):
        """Start ``node``'s slurmd in its network namespace, with its own hostname."""
        self._spawn_in(f"slurmd-{node}", self.ns(node), node, f"slurmd -D -N {node} -f {self.conf}")

    def _spawn_in(self, name, ns, hostname, command):
        """Start ``command`` in network namespace ``ns`` with a hostname of its own (the process's
        PID is the daemon's: nsenter, unshare and sh each exec the next)."""
        self._spawn(name, ["nsenter", f"--net=/run/netns/{ns}", "unshare", "--uts", "sh", "-c",
                           f"hostname {hostname} && exec {command}"])

    def _spawn(self, name, argv):
        log = open(self.root / f"{name}.out", "ab")
        env = dict(os.environ, SLURM_CONF=str(self.conf))
        self.procs[name] = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env,
                                            start_new_session=True)
        log.close()

    def node_pids(self, node):
        """Every process in ``node``'s network namespace (its slurmd, job steps and workers)."""
        return self._pids(self.ns(node))

    @staticmethod
    def _pids(ns):
        out = _run("ip", "netns", "pids", ns, check=False).stdout.split()
        return [int(p) for p in out if p.isdigit()]

    def kill_node(self, node):
        """Kill ``node``'s slurmd and every process on it (a node that dies)."""
        p = self.procs.pop(f"slurmd-{node}", None)
        for pid in ([p.pid] if p else []) + self.node_pids(node):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if p:
            p.wait()

    def stop(self):
        """Stop every process this cluster started (by PID) and delete its namespaces and links."""
        for node in self.nodes:
            if self.netns and self.ns(node) in self.netns:
                self.kill_node(node)
        for name in list(self.procs)[::-1]:
            p = self.procs.pop(name)
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(5)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        for ns in self.netns:
            for pid in self._pids(ns):  # anything a daemon left there (all of it started by this cluster)
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            _run("ip", "netns", "del", ns, check=False)  # its veth end goes with it, and so the host end
        self.netns = []
        for link in self.links[::-1]:
            _run("ip", "link", "del", link, check=False)
        self.links = []

    # -- SLURM commands -------------------------------------------------------------------
    def slurm(self, *args, check=True):
        """Run a SLURM command (``scontrol``, ``squeue``, ``sinfo``, ...) against this cluster."""
        return _run(*args, check=check, env=dict(os.environ, **self.env)).stdout

    def node_states(self):
        out = self.slurm("sinfo", "-h", "-N", "-o", "%N %T", check=False)
        return dict(line.split() for line in out.splitlines() if line.strip())

    def wait_idle(self, nodes, timeout=60):
        deadline = time.time() + timeout
        while True:
            states = self.node_states()
            if all(states.get(n, "").rstrip("*") in ("idle", "mixed", "allocated") for n in nodes):
                return
            if time.time() > deadline:
                raise RuntimeError(f"SLURM nodes not up after {timeout} s: {states}; slurmctld: "
                                   f"{self._tail(self.root / 'slurmctld.log')}")
            dead = [n for n, p in self.procs.items() if p.poll() is not None]
            if dead:
                raise RuntimeError(f"{dead[0]} exited: {self._tail(self.root / (dead[0] + '.out'))}")
            time.sleep(0.5)

    @staticmethod
    def _tail(path, n=1500):
        try:
            return Path(path).read_text(errors="replace")[-n:]
        except OSError:
            return "(no log)"
