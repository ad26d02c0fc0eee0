"""Beams from a configuration mapping: the scalar power beam of the Stokes-I path and, where
the beam type describes feeds, the E-field (Jones) beam of full-Stokes imaging.

Types (``spec["type"]``; parameters as in ``docs/configuration.md``):

* ``sin_elevation``, ``gaussian``, ``zernike``: scalar power beams (Stokes I only);
* ``short_dipole``: crossed short dipoles, x east and y north
  (:class:`mmflow.telescope.jones.ShortDipoleJones`); the power beam is
  ``A_I = (|J_x|^2 + |J_y|^2) / 2`` (:class:`mmflow.telescope.jones.JonesPowerBeam`);
* ``pyuvdata``: a beam file pyuvdata reads or one of its analytic beams; its Jones beam exists
  where the beam is an E-field beam.

One source for both paths: with a Jones-capable type, the Stokes-I power beam is derived from the
same Jones beam the full-Stokes transfer matrices use.
"""
from __future__ import annotations

import inspect

from mmflow.errors import InputError
from mmflow.telescope.beams import GaussianBeam, PyUVDataBeam, SinElevationBeam, ZernikeBeam
from mmflow.telescope.jones import JonesPowerBeam, PyUVDataJones, ShortDipoleJones

#: beam types whose parameters describe the feeds (a Jones beam)
JONES_TYPES = ("short_dipole", "pyuvdata")


def make_beam(spec):
    """The Stokes-I power beam of a config mapping (``{"type": "sin_elevation", "alpha": 1.5}`` etc.)."""
    return _build(spec, _make_beam)


def make_jones(spec):
    """The E-field beam of a config mapping (types ``short_dipole`` and E-field ``pyuvdata`` beams).

    Raises
    ------
    InputError
        For a scalar power-beam type or a pyuvdata power beam: they cannot describe Q, U, V.
    """
    kind = dict(spec).get("type", "sin_elevation")
    if kind not in JONES_TYPES:
        raise InputError("beam", "type", f"beam type '{kind}' is a scalar power beam: it cannot describe the "
                         "response of crossed feeds to Q, U and V",
                         "for imaging.stokes [I, Q, U, V] use beam type short_dipole or a pyuvdata E-field beam")
    return _build(spec, _make_jones)


def _build(spec, maker):
    try:
        return maker(dict(spec))
    except TypeError as exc:
        raise InputError("workflow", "beam", f"options {sorted(spec)} do not fit beam type "
                         f"'{spec.get('type')}' ({exc})", "replace the whole section: beam={type: ..., ...}") from None


def analytic_beam_class(cls_name):
    """The class ``pyuvdata.analytic_beam.<cls_name>`` (refused when pyuvdata has none)."""
    from pyuvdata import analytic_beam  # deferred: pyuvdata takes 2-3.5 s to import (docs/performance.md)

    cls = getattr(analytic_beam, cls_name, None)
    if cls is None:
        raise InputError("beam", "class", f"pyuvdata has no analytic beam '{cls_name}'",
                         "use e.g. GaussianBeam, AiryBeam, ShortDipoleBeam, UniformBeam")
    return cls


def required_params(cls_name, params=()):
    """The arguments of pyuvdata's analytic beam ``cls_name`` that its own signature requires (no
    default) and ``params`` lacks, in signature order: ``AiryBeam`` needs ``diameter``;
    ``ShortDipoleBeam`` and ``UniformBeam`` need nothing. (A class may check more itself, e.g.
    ``GaussianBeam`` one of ``sigma`` and ``diameter``: its error is reported when the beam is built.)"""
    sig = inspect.signature(analytic_beam_class(cls_name))
    return [n for n, p in sig.parameters.items() if p.default is inspect.Parameter.empty
            and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and n not in params]


def _pyuvdata_object(spec):
    """The file path or the analytic-beam object of a ``pyuvdata`` spec (popping its keys)."""
    if "file" in spec:
        return spec.pop("file")
    return analytic_beam_class(spec.pop("class", "GaussianBeam"))(**spec.pop("params", {}))


def _make_beam(spec):
    kind = spec.pop("type", "sin_elevation")
    if kind == "sin_elevation":
        return SinElevationBeam(**spec)
    if kind == "gaussian":
        return GaussianBeam(**spec)
    if kind == "zernike":
        return ZernikeBeam(**spec)
    if kind == "short_dipole":
        return JonesPowerBeam(ShortDipoleJones(**spec))
    if kind == "pyuvdata":
        return PyUVDataBeam(_pyuvdata_object(spec), **spec)
    raise InputError("beam", "type", f"unknown beam type '{kind}'",
                     "use sin_elevation, gaussian, zernike, short_dipole or pyuvdata")


def _make_jones(spec):
    kind = spec.pop("type")
    if kind == "short_dipole":
        return ShortDipoleJones(**spec)
    obj = _pyuvdata_object(spec)
    spec.pop("normalize", None)  # a Jones beam keeps its own normalisation
    return PyUVDataJones(obj, **spec)
