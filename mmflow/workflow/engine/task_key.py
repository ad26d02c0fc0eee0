"""Task keys: the names of a stage's units of work, with one format and one parse.

A stage's ``prepare`` (and ``next_cycle``) list :class:`TaskKey` values; the runner names the
completion marker of each task ``RUN/_status/STAGE/<key>.done`` after :meth:`TaskKey.format`
and hands the task :meth:`TaskKey.parse` of that name back. The strings are those earlier
versions wrote, so run directories made before this type existed resume unchanged.

The fields that are set choose the layout (``N`` an integer, zero-padded where shown):

=====================================  ====================  ==========================================
fields                                 string                stages
=====================================  ====================  ==========================================
``time``                               ``t00003``            simulate, ingest: a time chunk
``bl_chunk``                           ``b00002``            mmodes: a baseline chunk of ``vis.zarr``
``freq``                               ``f1``                products: a channel
``freq, time``                         ``f1_t00003``         peel: channel and time chunk
``freq, source``                       ``f1_s2``             models: channel and source
``freq, group``                        ``f1-g0004``          transfer: channel and baseline group
``freq, m_block``                      ``f1-m00032``         normal, solve, clean: channel and first m
``phase, freq``                        ``r1``                calibrate: ripple of a channel
``phase, freq, interval``              ``g1_00007``          calibrate: gains of a solution interval
``phase, freq, time``                  ``s1_t00003``         terrestrial: sums (``s``), amplitudes (``a``)
=====================================  ====================  ==========================================

Any of them may carry a cycle: ``c0002-f1-m00032`` is that task in cycle 2 of an iterative
stage (or the second phase, cycle 0, of a solve stage); the runner sets it.
"""
from __future__ import annotations

import re
import string
from dataclasses import dataclass, fields

#: layouts by the fields they hold (``cycle`` aside); ``{name:0Nd}`` is zero-padded to N digits
LAYOUTS = {
    ("time",): "t{time:05d}",
    ("bl_chunk",): "b{bl_chunk:05d}",
    ("freq",): "f{freq}",
    ("freq", "time"): "f{freq}_t{time:05d}",
    ("freq", "source"): "f{freq}_s{source}",
    ("freq", "group"): "f{freq}-g{group:04d}",
    ("freq", "m_block"): "f{freq}-m{m_block:05d}",
    ("phase", "freq"): "{phase}{freq}",
    ("phase", "freq", "interval"): "{phase}{freq}_{interval:05d}",
    ("phase", "time"): "{phase}_t{time:05d}",
    ("phase", "freq", "time"): "{phase}{freq}_t{time:05d}",
}
CYCLE = "c{cycle:04d}-"
#: letters that open a layout or the cycle prefix: never a phase (``f1`` is a channel, not phase ``f``)
RESERVED = "bcft"
PHASES = "".join(c for c in string.ascii_lowercase if c not in RESERVED)


def _pattern(template):
    """Regular expression of a layout: ``{x:0Nd}`` -> N or more digits, ``{x}`` -> digits, ``{phase}`` -> a letter."""
    out, pos = "", 0
    for m in re.finditer(r"\{(\w+)(?::0(\d+)d)?\}", template):
        out += re.escape(template[pos:m.start()])
        name, width = m.group(1), m.group(2)
        digits = rf"\d{{{width},}}" if width else r"\d+"
        out += f"(?P<{name}>{f'[{PHASES}]' if name == 'phase' else digits})"
        pos = m.end()
    return out + re.escape(template[pos:])


_BY_FIELDS = {frozenset(names): t for names, t in LAYOUTS.items()}
_PARSERS = [re.compile(f"(?:{_pattern(CYCLE)})?{_pattern(t)}") for t in LAYOUTS.values()]


@dataclass(frozen=True)
class TaskKey:
    """One task of a stage: which channel, time chunk, baseline group, m block, ... it works on.

    Parameters
    ----------
    freq : int, optional
        Channel index into ``vis.zarr``'s ``freqs_hz``.
    time : int, optional
        Time chunk ``i``: integrations :math:`[iT, \\min(N, (i+1)T))`
        (:func:`mmflow.workflow.engine.chunking.chunk_rows`).
    bl_chunk : int, optional
        Baseline (column) chunk of ``vis.zarr`` (the m-mode transform's unit).
    group : int, optional
        Baseline group of the transfer stage's plan.
    m_block : int, optional
        First m of an m block (``m0``; the block is :math:`[m_0, m_1)` of ``m_blocks``).
    source : int, optional
        Index into ``models.sources``.
    interval : int, optional
        Calibration solution interval.
    phase : str, optional
        One letter naming a stage's kind of task (not one of ``b c f t``): ``r`` ripple and
        ``g`` gains (calibrate), ``s`` sums and ``a`` amplitudes (terrestrial).
    cycle : int, optional
        Cycle of an iterative stage (or of a solve stage's second phase), set by the runner.

    Examples
    --------
    >>> TaskKey(freq=0, m_block=32).format()
    'f0-m00032'
    >>> TaskKey.parse("c0001-a_t00003")
    TaskKey(time=3, phase='a', cycle=1)
    """

    freq: int = None
    time: int = None
    bl_chunk: int = None
    group: int = None
    m_block: int = None
    source: int = None
    interval: int = None
    phase: str = None
    cycle: int = None

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "phase":
                if v is not None and (not isinstance(v, str) or len(v) != 1 or v not in PHASES):
                    raise ValueError(f"task key phase {v!r}: one lowercase letter, not one of {' '.join(RESERVED)}")
            elif v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
                raise ValueError(f"task key field {f.name}={v!r}: a non-negative integer")
        if frozenset(self._names()) not in _BY_FIELDS:
            raise ValueError(f"no task key has the fields {', '.join(self._names()) or '(none)'}: "
                             f"the layouts are {_listing()}")

    def _names(self):
        return tuple(f.name for f in fields(self) if f.name != "cycle" and getattr(self, f.name) is not None)

    def format(self):
        """The key as a string: the layout of its fields, after ``c<cycle>-`` when it has a cycle.

        Returns
        -------
        str
            E.g. ``'f1_t00003'`` or ``'c0002-f1-m00032'``; markers are named by it.
        """
        values = {n: getattr(self, n) for n in self._names()}
        body = _BY_FIELDS[frozenset(values)].format(**values)
        return body if self.cycle is None else CYCLE.format(cycle=self.cycle) + body

    __str__ = format

    def __repr__(self):
        set_ = ", ".join(f"{f.name}={getattr(self, f.name)!r}" for f in fields(self) if getattr(self, f.name) is not None)
        return f"TaskKey({set_})"

    @classmethod
    def parse(cls, text):
        """The key a string names: the inverse of :meth:`format`.

        Parameters
        ----------
        text : str
            A key as :meth:`format` writes it.

        Returns
        -------
        TaskKey
            The key ``k`` with ``k.format() == text``.

        Raises
        ------
        ValueError
            If ``text`` is not a key :meth:`format` writes (unknown layout, unpadded or over-padded
            numbers, stray characters).
        """
        if isinstance(text, str):
            for rx in _PARSERS:
                m = rx.fullmatch(text)
                if m is None:
                    continue
                values = {k: (v if k == "phase" else int(v)) for k, v in m.groupdict().items() if v is not None}
                key = cls(**values)
                if key.format() == text:
                    return key
        raise ValueError(f"malformed task key {text!r}: expected one of {_listing()}, optionally after "
                         f"a cycle prefix {CYCLE.format(cycle=0)}")


def _listing():
    return ", ".join(t.format(phase="<p>", freq=0, time=0, bl_chunk=0, group=0, m_block=0, source=0, interval=0)
                     for t in LAYOUTS.values())
