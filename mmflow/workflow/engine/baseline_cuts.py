"""The baseline cut of the solving stages (``calibrate``, ``peel``, ``models``, ``terrestrial``):
``min_baseline_lambda`` resolved per channel, and refused before any work when it leaves an antenna
without the baselines a solve needs.

The kernels (:mod:`mmflow.calibrate.baselines`) define the cut; this module turns a setting and a
field name into the mask a task uses and the message a user reads.
"""
from __future__ import annotations

from mmflow.calibrate.baselines import (antennas_short_of_baselines, auto_min_lambda, baseline_mask,
                                        resolve_min_lambda)
from mmflow.errors import InputError


def solve_mask(tel, pairs, setting, freq_hz):
    """Baselines a solve uses at ``freq_hz``: longer than ``setting`` (a number or ``"auto"``)."""
    return baseline_mask(pairs, tel.layout.enu, float(freq_hz), resolve_min_lambda(setting, pairs, tel.layout.enu,
                                                                                    float(freq_hz)))


def resolved_cuts(tel, pairs, setting):
    """The cut (wavelengths) of every channel, as the tasks use it (for the stores' attrs and summaries)."""
    return [round(resolve_min_lambda(setting, pairs, tel.layout.enu, float(f)), 4) for f in tel.freqs_hz]


def check_baselines(tel, pairs, setting, field):
    """Refuse, before any solve, a cut that leaves an antenna with data fewer than ``min(3, n)`` of its
    ``n`` cross baselines at some channel, naming the antennas, what each keeps, and the cut that
    would keep them (``auto``'s value)."""
    names = tel.layout.names
    for f in tel.freqs_hz:
        cut = resolve_min_lambda(setting, pairs, tel.layout.enu, float(f))
        short, kept, need = antennas_short_of_baselines(pairs, tel.layout.enu, float(f), cut)
        if short.size:
            listed = ", ".join(f"{names[a]} ({k} of {n} needed)" for a, k, n in zip(short[:12], kept, need))
            more = f" and {short.size - 12} more" if short.size > 12 else ""
            auto = auto_min_lambda(pairs, tel.layout.enu, float(f))
            raise InputError("workflow", field, f"{short.size} of {len(names)} antennas keep too few baselines "
                             f"longer than {cut:g} wavelengths at {f / 1e6:.3f} MHz: {listed}{more}",
                             f"set {field}=auto (here {auto:.2f}: every antenna keeps at least half of its "
                             f"baselines) or a value <= {auto:.2f}; or leave those antennas out of the input")
