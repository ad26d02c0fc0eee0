"""Configuration errors in words: where a value came from, what is wrong with it, and the fix.

Every value of a workflow comes from a YAML file (with a line number), a command-line
override (``section.key=value``) or a default. :class:`Origins` records which, so that an
error names it. Pydantic's errors and mmflow's own cross-field checks both become
:class:`Problem` records, reported together in one :class:`ConfigError`.
"""
from __future__ import annotations

import difflib
import json
import typing
from dataclasses import dataclass

import yaml
from pydantic import BaseModel

from mmflow.errors import InputError


@dataclass
class Problem:
    """One bad value: its location in the configuration, the value, what is wrong, the fix."""

    loc: tuple
    value: object
    problem: str
    fix: str


class ConfigError(InputError):
    """One or more bad values in a workflow configuration (each named with its origin).

    ``what``, ``field``, ``problem`` and ``fix`` are those of the first problem; ``problems``
    holds every ``(what, field, problem, fix)``; the message has one line per problem.
    """

    def __init__(self, lines):
        super().__init__(*lines[0])
        self.problems = list(lines)
        if len(lines) > 1:
            Exception.__init__(self, "\n".join(f"{w}: field '{f}': {p}. Fix: {x}" for w, f, p, x in lines))

    def __reduce__(self):  # as InputError's: an input error a task reports travels back to the driver
        return type(self), (self.problems,)


class BadValue(ValueError):
    """Raised inside field validators: ``problem`` in words and the ``fix``."""

    def __init__(self, problem, fix):
        super().__init__(problem)
        self.problem, self.fix = problem, fix


def show(value, width=60):
    """A value as the user would write it (strings quoted), shortened to ``width`` characters."""
    text = repr(value) if isinstance(value, str) else json.dumps(value, default=str)
    return text if len(text) <= width else text[: width - 3] + "..."


def nearest(word, candidates):
    """The candidate closest to ``word`` (difflib), or None."""
    hit = difflib.get_close_matches(str(word), [str(c) for c in candidates], n=1, cutoff=0.6)
    return hit[0] if hit else None


class Origins:
    """Where each value came from: ``{loc tuple: text}``, the longest recorded prefix wins."""

    def __init__(self, default="<defaults>"):
        self.default = default
        self._by_loc = {}

    def add_yaml(self, path, text):
        """Record the line of every key of a YAML document (``yaml.compose`` keeps marks)."""
        node = yaml.compose(text, Loader=yaml.SafeLoader)

        def walk(n, prefix):
            if isinstance(n, yaml.MappingNode):
                for k, v in n.value:
                    loc = prefix + (str(k.value),)
                    self._by_loc[loc] = f"{path}, line {k.start_mark.line + 1}"
                    walk(v, loc)

        if node is not None:
            walk(node, ())

    def add_override(self, loc, text):
        """An override replaces everything under ``loc`` (``beam={...}`` replaces the section)."""
        for k in [k for k in self._by_loc if k[: len(loc)] == loc]:
            del self._by_loc[k]
        self._by_loc[loc] = f"command-line override '{text}'"

    def of(self, loc):
        loc = tuple(loc)
        for i in range(len(loc), 0, -1):
            hit = self._by_loc.get(loc[:i])
            if hit is not None:
                return hit
        below = [k for k in self._by_loc if k[: len(loc)] == loc]
        if loc and below:  # an unknown section: name the key inside it that the user wrote
            return self._by_loc[min(below, key=len)]
        return f"{self.default} (default value)"


def report(problems, origins):
    """Raise one :class:`ConfigError` for ``problems`` (nothing when the list is empty)."""
    if not problems:
        return
    lines = []
    for p in problems:
        field = ".".join(str(x) for x in p.loc) or "(top level)"
        problem = p.problem
        if p.value is not None and not problem.startswith(show(p.value)):
            problem = f"{show(p.value)}: {problem}"
        lines.append((origins.of(p.loc), field, problem, p.fix))
    raise ConfigError(lines)


def yaml_error(where, exc):
    """An InputError for a YAML syntax error, with the line and column of the error."""
    mark = getattr(exc, "problem_mark", None)
    if mark is not None:
        where = f"{where}, line {mark.line + 1} column {mark.column + 1}"
    problem = " ".join(str(x) for x in (getattr(exc, "context", None), getattr(exc, "problem", None)) if x)
    return InputError(where, "YAML syntax", f"not valid YAML ({problem or exc})",
                      "write 'key: value' pairs indented with spaces (no tabs), and quote strings that "
                      "contain ':', '#', '{' or '['")


# ----------------------------------------------------------------------------- schema words

def _typename(ann):
    origin = typing.get_origin(ann)
    args = typing.get_args(ann)
    if origin is typing.Annotated:  # a type with validators (a path, a baseline cut): name the type
        return _typename(args[0])
    if origin is typing.Literal:
        return "one of " + " | ".join(str(a) for a in args)
    if origin is typing.Union:
        inner = [a for a in args if a is not type(None)]
        text = " or ".join(_typename(a) for a in inner)
        return text + (", or null" if len(inner) < len(args) else "")
    if origin is list:
        inner = _typename(args[0]) if args else "values"
        plural = {"a number": "numbers", "an integer": "integers", "text": "strings"}
        if inner.startswith("a list of "):
            return "a list of lists of " + inner.removeprefix("a list of ")
        return "a list of " + plural.get(inner, inner)
    if origin is dict or ann is dict:
        return "a mapping"
    words = {int: "an integer", float: "a number", bool: "true | false", str: "text"}
    return words.get(ann, getattr(ann, "__name__", str(ann)))


def allowed_text(field):
    """The values a pydantic field accepts, in words (``"an integer >= 1"``, ``"one of a | b"``)."""
    extra = field.json_schema_extra or {}
    if "allowed" in extra:
        return extra["allowed"]
    text = _typename(field.annotation)
    bounds = []
    for m in field.metadata:
        for attr, sym in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            if getattr(m, attr, None) is not None:
                bounds.append(f"{sym} {getattr(m, attr)}")
        if getattr(m, "min_length", None) is not None:
            bounds.append(f"(at least {m.min_length})")
    if bounds:
        head, sep, tail = text.partition(", or null")
        text = f"{head} {', '.join(bounds)}{sep}{tail}"
    return text


def field_at(model_cls, loc):
    """The pydantic ``FieldInfo`` at ``loc`` below ``model_cls`` (None past lists or unknown keys)."""
    field = None
    cls = model_cls
    for part in loc:
        if cls is None or not isinstance(part, str) or part not in cls.model_fields:
            by_alias = {f.alias: f for f in cls.model_fields.values() if f.alias} if cls is not None else {}
            if cls is None or part not in by_alias:
                return None
            field = by_alias[part]
        else:
            field = cls.model_fields[part]
        ann = field.annotation
        cls = ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None
    return field


def section_keys(model_cls, loc):
    """The option names valid at ``loc`` (the section containing an unknown key)."""
    if not loc:
        return list(model_cls.model_fields)
    f = field_at(model_cls, loc)
    ann = getattr(f, "annotation", None)
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return [fi.alias or name for name, fi in ann.model_fields.items()]
    return []


def all_dotted_keys(model_cls, prefix=()):
    out = []
    for name, f in model_cls.model_fields.items():
        loc = prefix + (f.alias or name,)
        out.append(".".join(loc))
        if isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel):
            out.extend(all_dotted_keys(f.annotation, loc))
    return out


def unknown_key_fix(model_cls, loc, extra_keys=(), prefix=()):
    """Fix for an unknown key: the nearest valid key in its section, or the same key elsewhere."""
    section, key = tuple(loc[:-1]), str(loc[-1])
    keys = list(section_keys(model_cls, section)) + list(extra_keys)
    where = ".".join(section)
    hit = nearest(key, keys)
    if hit is not None:
        return f"did you mean '{'.'.join(tuple(prefix) + section + (hit,))}'?"
    dotted = all_dotted_keys(model_cls)
    elsewhere = [k for k in dotted if k.split(".")[-1] == key]
    if elsewhere:
        return f"'{key}' is an option of {', '.join(repr(k) for k in elsewhere)}: move it there"
    hit = nearest(".".join(map(str, loc)), dotted)
    if hit is not None:
        return f"did you mean '{hit}'?"
    return f"remove it; the options of {where or 'the top level'} are {', '.join(keys)}"


def from_pydantic(errors, model_cls, extra_keys=None, prefix=()):
    """Turn ``ValidationError.errors()`` into :class:`Problem` records with fixes.

    ``extra_keys``: ``{section loc: names}`` also valid there (beam parameters);
    ``prefix``: the location of ``model_cls`` in the whole configuration.
    """
    out = []
    for e in errors:
        loc, value, kind = tuple(e["loc"]), e.get("input"), e["type"]
        field = field_at(model_cls, loc)
        loc = tuple(prefix) + loc
        name = ".".join(map(str, loc))
        ctx = e.get("ctx") or {}
        if kind == "extra_forbidden":
            sec = ".".join(map(str, loc[:-1])) or "the top level"
            fix = unknown_key_fix(model_cls, loc[len(prefix):], (extra_keys or {}).get(loc[:-1], ()), prefix)
            out.append(Problem(loc, value, f"'{loc[-1]}' is not an option of {sec} (Extra inputs are not permitted)",
                               fix))
            continue
        if isinstance(ctx.get("error"), BadValue):
            err = ctx["error"]
            shown = "" if isinstance(value, dict) else f"{show(value)}: "  # a whole section: name it, not its text
            out.append(Problem(loc, None if shown == "" else value, shown + err.problem, err.fix))
            continue
        if kind in ("model_type", "model_attributes_type", "dict_type"):
            out.append(Problem(loc, value, f"{show(value)} is not a section of options",
                               f"write {name} as a mapping, e.g. '{name}: {{key: value}}' (see `mmflow config show`)"))
            continue
        allowed = allowed_text(field) if field is not None else "a valid value"
        default = None if field is None or field.is_required() else field.default
        fix = f"set {name} to {allowed}"
        if kind == "literal_error":
            hit = nearest(value, [a.strip() for a in ctx.get("expected", "").replace("'", "").split(" or ")
                                  for a in a.split(",")])
            if hit:
                fix = f"did you mean '{hit}'? ({name}: {allowed})"
        if default is not None and "did you mean" not in fix:
            fix += f" (default: {show(default)})"
        msg = e["msg"].replace("Value error, ", "")
        out.append(Problem(loc, value, f"{show(value)} is not allowed ({msg[0].lower() + msg[1:]})", fix))
    return out
