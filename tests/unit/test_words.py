"""Words that stay true: every ``mmflow.`` dotted reference in the docs and docstrings resolves, and no
tracked file holds a path of the machine that wrote it.

A rename that leaves ``mmflow.workflow.old_module.gone`` in ``docs/planning.md`` sends the next reader to
nothing; these tests name every such reference with its file and line.
"""
from __future__ import annotations

import importlib
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

#: a dotted reference: ``mmflow`` and at least one more identifier, in docs or source text
DOTTED = re.compile(r"(?<![\w./-])mmflow(?:\.[A-Za-z_]\w*)+")


def tracked_files():
    """The repository's tracked files (``git ls-files``), or the test is skipped outside a checkout."""
    try:
        out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: the tracked files are unknown")
    return [ROOT / f for f in out.split()]


def resolves(ref):
    """True when ``ref`` names a module, or an attribute reachable from the longest importable prefix."""
    parts = ref.split(".")
    for n in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:n]))
        except ImportError:
            continue
        for name in parts[n:]:
            if hasattr(obj, name):
                obj = getattr(obj, name)
            elif name in getattr(obj, "__annotations__", {}):  # a dataclass or model field without a default
                obj = None
            else:
                return False
        return True
    return False


def dotted_references(paths):
    """``(file, line, reference)`` of every dotted ``mmflow.`` reference in ``paths``."""
    out = []
    for p in paths:
        for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if "getLogger(" in line:  # logger names are not modules
                continue
            for m in DOTTED.finditer(line):
                ref = m.group(0).rstrip(".")
                if ref.endswith((".py", ".md", ".json", ".yaml", ".zarr", ".log")):
                    continue
                out.append((p.relative_to(ROOT), i, ref))
    return out


def test_every_dotted_reference_resolves():
    files = [p for p in tracked_files() if p.is_file() and p.suffix in (".py", ".md")
             and p.relative_to(ROOT).parts[0] in ("mmflow", "docs", "README.md", "workflows")]
    refs = dotted_references(files)
    assert len(refs) > 100, "the scan found too few references: is the pattern still right?"
    bad = [f"{f}:{line}: {ref}" for f, line, ref in refs if not resolves(ref)]
    assert not bad, "references to nothing (rename them to what exists now):\n" + "\n".join(bad)


def test_resolver_tells_a_live_name_from_a_dead_one():
    assert resolves("mmflow.workflow.pipeline.PIPELINE")
    assert resolves("mmflow.conventions")
    assert not resolves("mmflow.workflow.pipeline.NO_SUCH_NAME")
    assert not resolves("mmflow.no_such_module")


#: a path of the machine a file was written on (built in pieces so this file does not match itself)
MACHINE_PATH = re.compile("(?:/" + "work|/" + "root|/" + r"home/\w)/")


def test_no_machine_paths_in_tracked_files():
    bad = []
    for p in tracked_files():
        if not p.is_file() or p.suffix in (".gz", ".uvh5", ".fits", ".png", ".whl"):
            continue
        try:
            text = p.read_text()
        except UnicodeDecodeError:
            continue
        bad += [
            f"{p.relative_to(ROOT)}:{i}" for i, line in enumerate(text.splitlines(), 1) if MACHINE_PATH.search(line)
        ]
    assert not bad, "machine paths (use paths relative to the repository or a run directory):\n" + "\n".join(bad)


#: a path of a module in the repository, as docs cite them (``mmflow/workflow/engine/runner.py``)
MODULE_PATH = re.compile(r"(?<![\w/.-])((?:mmflow|tests|benchmarks|workflows|docs)/[\w/.-]+\.(?:py|md|yaml))")


def test_every_cited_repository_path_exists():
    files = [p for p in tracked_files() if p.is_file() and p.suffix in (".py", ".md")
             and p.relative_to(ROOT).parts[0] in ("mmflow", "docs", "README.md")]
    bad = []
    for p in files:
        for i, line in enumerate(p.read_text().splitlines(), 1):
            bad += [f"{p.relative_to(ROOT)}:{i}: {m}" for m in MODULE_PATH.findall(line) if not (ROOT / m).exists()]
    assert not bad, "paths to files that are not in the repository:\n" + "\n".join(bad)
