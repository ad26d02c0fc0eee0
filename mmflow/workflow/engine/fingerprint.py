"""What a stage's output depends on, and a guard that it reads nothing else.

A stage declares the configuration fields it reads (``Stage.config``, dotted paths such as
``"imaging"`` or ``"products.frame"``), the stores it reads (``Stage.inputs``) and, where it
reads files the user gives (input data, a prior map), those files (``Stage.files``). Its
fingerprint is the hash of

* the values of its declared configuration fields,
* the fingerprints of the stages that wrote its input stores,
* the names and content digests of its input files.

:class:`ConfigView` makes the declaration binding: stage code sees the configuration
through a view that raises :class:`UndeclaredConfigRead` on any field the stage did not
declare, so a fingerprint cannot silently miss a setting (the test suite runs every stage).
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from pydantic import BaseModel

from mmflow.errors import InputError


class UndeclaredConfigRead(AttributeError):
    """Stage code read a configuration field its ``Stage.config`` does not declare (a bug)."""


def _covered(path, allowed):
    return any(path == a or path.startswith(a + ".") for a in allowed)


def _leads_to(path, allowed):
    return any(a.startswith(path + ".") for a in allowed)


class ConfigView:
    """Read-only view of a pydantic config that admits only the declared dotted paths."""

    __slots__ = ("_obj", "_allowed", "_prefix", "_stage")

    def __init__(self, obj, allowed, stage, prefix=""):
        object.__setattr__(self, "_obj", obj)
        object.__setattr__(self, "_allowed", tuple(allowed))
        object.__setattr__(self, "_prefix", prefix)
        object.__setattr__(self, "_stage", stage)

    def __getattr__(self, name):
        path = f"{self._prefix}.{name}" if self._prefix else name
        if name in ("model_dump", "model_dump_json"):
            if not _covered(self._prefix, self._allowed):
                raise UndeclaredConfigRead(f"stage '{self._stage}' dumps '{self._prefix}' without declaring it")
            return getattr(self._obj, name)
        value = getattr(self._obj, name)
        if _covered(path, self._allowed):
            return value
        if isinstance(value, BaseModel) and _leads_to(path, self._allowed):
            return ConfigView(value, self._allowed, self._stage, path)
        raise UndeclaredConfigRead(f"stage '{self._stage}' reads '{path}', which its Stage.config "
                                   f"{self._allowed} does not declare: its fingerprint would miss it")

    def __setattr__(self, name, value):
        raise AttributeError("the configuration is read-only inside a stage")


def config_values(cfg, paths):
    """``{path: value}`` of the declared dotted paths (sections dumped whole, less what a field's
    ``json_schema_extra`` exempts: ``"fingerprint": False`` leaves the field out, ``"fingerprint_as": v``
    records ``v`` whatever its value -- for settings that reach a stage's output only through an
    input file the fingerprint digests, e.g. ``mmode.prior_passes`` through the prior's alm, ``v``
    the value runs recorded before the exemption, so that their fingerprints stay)."""
    out = {}
    for p in paths:
        obj = cfg
        for part in p.split("."):
            obj = getattr(obj, part)
        out[p] = _section_values(obj) if isinstance(obj, BaseModel) else obj
    return out


def _section_values(section):
    """A section's dump with its fields' fingerprint exemptions applied (:func:`config_values`)."""
    extras = {name: f.json_schema_extra for name, f in type(section).model_fields.items()
              if isinstance(f.json_schema_extra, dict)}
    out = section.model_dump(mode="json", exclude={n for n, e in extras.items() if e.get("fingerprint") is False})
    out.update({n: e["fingerprint_as"] for n, e in extras.items() if "fingerprint_as" in e})
    return out


def _flatten(prefix, value, out):
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(f"{prefix}.{k}", v, out)
    else:
        out[prefix] = value
    return out


def file_digest(path, known=None):
    """SHA-1 of a file's (or a directory's, e.g. a MeasurementSet) contents.

    ``known``: ``{path: [size, mtime_ns, digest]}`` of an earlier run; a file whose size and
    modification time are unchanged is not read again. Returns ``[size, mtime_ns, digest]``.
    """
    p = Path(path)
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    if not p.exists():
        raise InputError(str(p), "file", "does not exist", "check the path in the configuration")
    stats = [f.stat() for f in files]
    size, mtime = sum(s.st_size for s in stats), max((s.st_mtime_ns for s in stats), default=0)
    old = (known or {}).get(str(p))
    if old and old[0] == size and old[1] == mtime:
        return old
    h = hashlib.sha1()
    for f in files:
        h.update(str(f.relative_to(p) if p.is_dir() else f.name).encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 24), b""):
                h.update(block)
    return [size, mtime, h.hexdigest()]


@dataclass
class StageFingerprint:
    """Settings, upstream fingerprints and input-file digests of one stage."""

    settings: dict
    upstream: dict
    files: dict = field(default_factory=dict)

    @property
    def digest(self):
        blob = json.dumps({"settings": self.settings, "upstream": self.upstream,
                           "files": {k: v[2] for k, v in self.files.items()}}, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def record(self):
        return {"fingerprint": self.digest, "settings": self.settings, "upstream": self.upstream,
                "files": self.files}

    def explain(self, old):
        """Why a stored manifest ``old`` differs: the changed settings, inputs and files, in words."""
        why = []
        a = _flatten("", old.get("settings", {}), {})
        b = _flatten("", self.settings, {})
        for k in sorted(set(a) | set(b)):
            if a.get(k, "<unset>") != b.get(k, "<unset>"):
                why.append(f"{k.lstrip('.')}: {a.get(k, '<unset>')} -> {b.get(k, '<unset>')}")
        for st in sorted(set(old.get("upstream", {})) | set(self.upstream)):
            if old.get("upstream", {}).get(st) != self.upstream.get(st):
                why.append(f"its input from stage '{st}' changed")
        oldf = old.get("files", {})
        for f in sorted(set(oldf) | set(self.files)):
            if f not in oldf:
                why.append(f"new input file {f}")
            elif f not in self.files:
                why.append(f"input file {f} is gone")
            elif oldf[f][2] != self.files[f][2]:
                why.append(f"input file {f} changed since it was read")
        return "; ".join(why) or "unknown change (an older mmflow version?)"


def stage_file_digests(paths, old_manifest):
    known = (old_manifest or {}).get("files", {})
    return {os.path.abspath(p): file_digest(os.path.abspath(p), known) for p in paths}
