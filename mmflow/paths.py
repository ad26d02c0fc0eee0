"""The one rule for paths a user writes: ``~`` and environment variables expanded, everywhere.

A setting (``run.directory``, ``input.path``, ``telescope.layout_file``, ``beam.file``,
``mmode.prior_run``, ``cluster.jobqueue.log_directory``), a command-line argument or a record's path
goes through :func:`expand_path` before it is used, so ``~/layout.txt`` and ``$SCRATCH/runs`` mean
the same wherever they are read.
"""
from __future__ import annotations

import os


def expand_path(path):
    """``path`` with ``$VAR`` / ``${VAR}`` and then ``~`` expanded (``os.path.expandvars``, ``expanduser``).

    Parameters
    ----------
    path : str or os.PathLike
        As the user wrote it; variables that are not set are left as written.

    Returns
    -------
    str
        The expanded path (not made absolute, not checked for existence).
    """
    return os.path.expanduser(os.path.expandvars(os.fspath(path)))
