"""The compute nodes a cluster plan lays a run onto: from ``sinfo`` where SLURM answers, else as given.

``sinfo -h -o '%c %m %D %P'`` prints, per group of alike nodes of a partition, the CPUs of a node,
its memory in MB (SLURM's ``RealMemory``: what jobs may ask for), the nodes of the group and the
partition (``*`` marks the default one); a ``+`` after a figure says some nodes of the group have
more. :func:`node_size` reads it, or takes ``--node-cores`` / ``--node-memory`` (which win), and
refuses, naming both, where neither is at hand.
"""
from __future__ import annotations

import math
import shutil
import subprocess
from dataclasses import dataclass
from typing import Optional

from mmflow.errors import InputError

#: the ``sinfo`` call whose output :func:`parse_sinfo` reads
SINFO_COMMAND = ("sinfo", "-h", "-o", "%c %m %D %P")
#: bytes of SLURM's memory unit (``%m``: megabytes, as SLURM counts them)
SLURM_MB = 1024 ** 2
MIB = 1024 ** 2
GIB = 1024 ** 3
#: a batch job's own ``dask worker`` process (the nannies of its workers), once a job whatever its workers: it
#: imports the workers' ``--preload`` (``mmflow.workflow.engine.batch.WORKER_PRELOAD``: the stages and numba's
#: runtime) to check its arguments (``distributed.preloading.validate_preload_argv``), so it holds about what a
#: worker does: 0.305 GB resident beside each worker's 0.323 GB (one or two workers a job, measured 2026-11-28;
#: docs/clusters.md). SLURM's memory limit counts it with the job's workers; dask's limit for each worker does not
JOB_PROCESS_BYTES = 296 * MIB


@dataclass(frozen=True)
class Node:
    """One compute node: its cores and the memory a job may use on it; ``count``: the nodes of its
    kind in the partition (None where not known); ``source``: where the sizes came from."""

    cores: int
    memory_bytes: float
    count: Optional[int] = None
    partition: Optional[str] = None
    source: str = "given"

    @property
    def job_memory_bytes(self):
        """The most memory a job may ask for on the node: whole GiB (dask-jobqueue asks SLURM for a
        job's memory rounded up to whole GiB, so a request a fraction above would exceed the node and
        never start)."""
        return math.floor(self.memory_bytes / GIB) * GIB

    @property
    def core_memory_bytes(self):
        """Memory per core, whole MiB: a standard worker's (one core), of what a job may ask for less its own
        process (:data:`JOB_PROCESS_BYTES`); a job of ``n`` cores asks for ``n`` of them and its process
        (:func:`job_memory`), at most :attr:`job_memory_bytes`."""
        return math.floor((self.job_memory_bytes - JOB_PROCESS_BYTES) / self.cores / MIB) * MIB


def job_memory(cores, core_memory_bytes):
    """A job's memory as dask-jobqueue takes it (whole MiB, e.g. ``"99008MiB"``): ``cores`` core shares and the
    job's own process, :math:`n_{cores} s + J` (:data:`JOB_PROCESS_BYTES`); dask-jobqueue gives each of the job's
    ``processes`` workers :math:`1/p` of it, so a worker's limit is at least its shares."""
    return f"{(cores * core_memory_bytes + JOB_PROCESS_BYTES) // MIB}MiB"


def parse_sinfo(text):
    """The node groups of ``sinfo -h -o '%c %m %D %P'`` output.

    Parameters
    ----------
    text : str
        The command's output, one group a line: cores, memory (MB), node count, partition.

    Returns
    -------
    list of dict
        Per line ``partition``, ``default`` (the partition marked ``*``), ``cores``, ``memory_bytes``
        and ``nodes`` (a ``+`` after a figure is dropped: the smallest node of the group is planned).

    Raises
    ------
    InputError
        A line that is not four fields of those kinds.
    """
    groups = []
    for line in text.splitlines():
        if not line.strip():
            continue
        fields = line.split()
        try:
            if len(fields) != 4:
                raise ValueError(line)
            cores, mem, count = (int(f.rstrip("+")) for f in fields[:3])
        except ValueError:
            raise InputError("sinfo", " ".join(SINFO_COMMAND), f"cannot read the line {line!r}",
                             "give the node's size with --node-cores and --node-memory") from None
        part = fields[3]
        groups.append({"partition": part.rstrip("*"), "default": part.endswith("*"), "cores": cores,
                       "memory_bytes": float(mem) * SLURM_MB, "nodes": count})
    return groups


def node_from_sinfo(text, partition=None):
    """The :class:`Node` of a partition (default: the one marked ``*``, else the first listed) from
    ``sinfo`` output: the node kind with the most nodes; ``count`` the partition's nodes in all."""
    groups = parse_sinfo(text)
    if not groups:
        raise InputError("sinfo", " ".join(SINFO_COMMAND), "lists no nodes",
                         "give the node's size with --node-cores and --node-memory")
    if partition is None:
        partition = next((g["partition"] for g in groups if g["default"]), groups[0]["partition"])
    mine = [g for g in groups if g["partition"] == partition]
    if not mine:
        raise InputError("sinfo", "partition", f"no partition {partition!r} (sinfo lists "
                         f"{', '.join(sorted({g['partition'] for g in groups}))})", "name one of those")
    kind = max(mine, key=lambda g: g["nodes"])
    return Node(kind["cores"], kind["memory_bytes"], sum(g["nodes"] for g in mine), partition, "sinfo")


def read_sinfo():
    """``sinfo``'s output, or None where SLURM's commands are not on this machine or do not answer."""
    if shutil.which(SINFO_COMMAND[0]) is None:
        return None
    try:
        out = subprocess.run(SINFO_COMMAND, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout if out.returncode == 0 and out.stdout.strip() else None


def node_size(cores=None, memory=None, partition=None, sinfo_text=None, scheduler="slurm"):
    """The :class:`Node` to plan on: ``cores`` and ``memory`` (bytes, or text such as ``"128GB"``)
    where given, the rest from ``sinfo`` (``sinfo_text``, else :func:`read_sinfo`; SLURM's only: for
    another ``scheduler`` both must be given).

    Raises
    ------
    InputError
        Neither given nor ``sinfo`` at hand: naming the options that give the size.
    """
    from dask.utils import parse_bytes  # deferred: dask takes 0.3-0.8 s to import

    mem = parse_bytes(memory) if isinstance(memory, str) else memory
    if cores is not None and mem is not None:
        return Node(int(cores), float(mem), None, partition, "given")
    text = sinfo_text if sinfo_text is not None else read_sinfo() if scheduler == "slurm" else None
    if text is None:
        why = ("no sinfo on this machine to read the nodes' cores and memory from" if scheduler == "slurm" else
               f"the nodes' cores and memory are read from SLURM's sinfo only, not from {scheduler}")
        raise InputError("cluster", "node size", why,
                         "give them: --node-cores 32 --node-memory 128GB (and --nodes to plan on)")
    found = node_from_sinfo(text, partition)
    source = "sinfo" if cores is None and mem is None else "sinfo and given"
    return Node(int(cores or found.cores), float(mem or found.memory_bytes), found.count,
                found.partition, source)
