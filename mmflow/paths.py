"""The one rule for paths a user writes: ``~`` and environment variables expanded, everywhere.

A setting (``run.directory``, ``input.path``, ``telescope.layout_file``, ``beam.file``,
``mmode.prior_run``, ``cluster.jobqueue.log_directory``), a command-line argument or a record's path
goes through :func:`expand_path` before it is used, so ``~/layout.txt`` and ``$SCRATCH/runs`` mean
the same wherever they are read.
"""
from __future__ import annotations

import getpass
import os
import re


def expand_path(path):
    """``path`` with ``$VAR`` / ``${VAR}`` and then ``~`` expanded (``os.path.expandvars``, ``expanduser``).
    ``$USER`` where it is not set (containers, cron, some batch jobs) is the login name
    (``getpass.getuser``), as ``~`` is the home directory without ``$HOME``.

    Parameters
    ----------
    path : str or os.PathLike
        As the user wrote it; variables that are not set are left as written.

    Returns
    -------
    str
        The expanded path (not made absolute, not checked for existence).
    """
    text = os.fspath(path)
    if "USER" not in os.environ and re.search(_USER, text):
        try:
            text = re.sub(_USER, getpass.getuser(), text)
        except (OSError, KeyError):  # no login name either: left as written
            pass
    return os.path.expanduser(os.path.expandvars(text))


_USER = r"\$(\{USER\}|USER\b)"
