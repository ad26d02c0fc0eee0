"""E-field (Jones) beams of crossed dual-polarisation feeds, for full-Stokes transfer matrices.

A feed p's voltage is ``v_p = J_p . E``: ``J_p(r)`` is a complex vector transverse to the
direction ``r`` (the effective length, dimensionless here), ``E`` the sky's electric field.
The correlation of feeds p (antenna i) and q (antenna j) through a sky of coherency
``<E E^H>`` is ``J_p <E E^H> J_q^H`` -- the convention of matvis and pyuvsim.

Feeds are ``("x", "y")`` with the OVRO-LWA's geometry: **x east, y north**.

Components. :meth:`JonesBeam.jones` gives, per feed, ``(J_theta, J_phi)`` on the local
spherical basis with ``theta`` the zenith angle: ``e_theta`` points away from the zenith
(towards the horizon) and ``e_phi = r x e_theta`` (so ``(r, e_theta, e_phi)`` is right-handed):
``e_phi`` is the direction of increasing pyuvdata azimuth (east through north), i.e. of
*decreasing* mmflow azimuth (north through east). In ENU components, with mmflow azimuth
``az``::

    r       = (sin za sin az, sin za cos az,  cos za)
    e_theta = (cos za sin az, cos za cos az, -sin za)
    e_phi   = (-cos az,       sin az,         0)

pyuvdata's E-field beams give ``(J . az_hat, J . za_hat)`` with its own azimuth, which are
``(J_phi, J_theta)`` here.

Stokes-I power beam. For an unpolarised sky ``<E E^H> = I 1`` (mmflow's ``avg``
convention: ``V_xx = int |J_x|^2 I ...``), so the Stokes-I response of
``V_I = (V_xx + V_yy) / 2`` is ``A_I = (|J_x|^2 + |J_y|^2) / 2`` with ``|J|^2 = J . J^*``
(:meth:`JonesBeam.power`; :class:`JonesPowerBeam` makes it a scalar :class:`Beam` for the
Stokes-I path). For a short dipole ``A_I = 1 - sin^2(za) / 2``, 1 at zenith.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from mmflow.conventions import enu_to_azza
from mmflow.errors import InputError
from mmflow.telescope.beams import Beam, BeamModel, beam_freq_range, read_pyuvdata_beam

#: Feed labels, in the order of the first axis of every Jones array: x east, y north.
FEEDS = ("x", "y")


def local_basis(az, za):
    """ENU components of ``(e_theta, e_phi)`` (see module docstring); shape ``(2, 3) + az.shape``."""
    az, za = np.broadcast_arrays(np.asarray(az, float), np.asarray(za, float))
    sa, ca, sz, cz = np.sin(az), np.cos(az), np.sin(za), np.cos(za)
    e_theta = np.stack([cz * sa, cz * ca, -sz])
    e_phi = np.stack([-ca, sa, np.zeros_like(az)])
    return np.stack([e_theta, e_phi])


class JonesBeam(BeamModel):
    """Base class: subclasses implement :meth:`_jones` for directions above the horizon.

    Attributes
    ----------
    lmax_hint : int
        Angular band limit of the beam products ``J_p J_q^*`` (sizes quadrature grids, as
        :attr:`mmflow.telescope.beams.Beam.lmax_hint`).
    """

    lmax_hint = 24
    name = "jones"

    def jones(self, az, za, freq_hz):
        """``(J_theta, J_phi)`` of feeds x, y at mmflow azimuth ``az``, zenith angle ``za``.

        Returns
        -------
        ndarray, complex, shape ``(2, 2) + az.shape``: ``[feed, component]``, zero below the horizon.
        """
        return self._above_horizon(self._jones, az, za, freq_hz, lead=(2, 2), dtype=complex)

    def jones_enu(self, enu, freq_hz):
        """The feeds' response vectors in ENU components, ``J_p = J_theta e_theta + J_phi e_phi``.

        Parameters
        ----------
        enu : ndarray (..., 3) unit vectors (east, north, up)

        Returns
        -------
        ndarray, complex, shape ``(2, 3) + enu.shape[:-1]``: ``[feed, east/north/up]``.
        """
        az, za = enu_to_azza(np.asarray(enu, float))
        comp = self.jones(az, za, freq_hz)  # (2 feeds, 2 comps, ...)
        basis = local_basis(az, za)  # (2 comps, 3, ...)
        return np.einsum("pc...,ci...->pi...", comp, basis)

    def power(self, az, za, freq_hz, feed=None):
        """Stokes-I power response ``A_I = (|J_x|^2 + |J_y|^2) / 2`` (``avg`` convention), or with
        ``feed`` (``"x"``, ``"y"``) that feed's ``|J_p|^2``: its parallel hand's response to an
        unpolarised sky (``V_pp = int |J_p|^2 I ...``)."""
        j = self.jones(az, za, freq_hz)
        if feed is not None:
            return np.sum(np.abs(j[FEEDS.index(feed)]) ** 2, axis=0)
        return 0.5 * np.sum(np.abs(j) ** 2, axis=(0, 1))

    def power_beam(self, feed=None):
        """The derived Stokes-I power beam (or one feed's, ``feed``) as a scalar
        :class:`mmflow.telescope.beams.Beam`."""
        return JonesPowerBeam(self, feed)

    def _jones(self, az, za, freq_hz):
        raise NotImplementedError


class ShortDipoleJones(JonesBeam):
    """Crossed short (Hertzian) dipoles, x east and y north: ``J_p = d_p - (d_p . r) r``.

    Components (mmflow azimuth ``az``)::

        J_x = (cos za sin az, -cos az)      J_y = (cos za cos az, sin az)

    times ``cos(za)^horizon_taper`` (default 0: exactly pyuvdata's ``ShortDipoleBeam``,
    whose response does not vanish at the horizon; a taper makes the beam products smooth
    there, e.g. a ground screen, and the quadrature converge fast).
    """

    name = "short_dipole"

    def __init__(self, horizon_taper=0.0, lmax_hint=24):
        if horizon_taper < 0:
            raise InputError("jones beam", "horizon_taper", f"{horizon_taper} < 0", "use 0 or a positive power")
        self.horizon_taper = float(horizon_taper)
        self.lmax_hint = int(lmax_hint)

    def _jones(self, az, za, freq_hz):
        sa, ca, cz = np.sin(az), np.cos(az), np.cos(za)
        out = np.array([[cz * sa, -ca], [cz * ca, sa]], dtype=complex)
        if self.horizon_taper:
            out *= cz ** self.horizon_taper
        return out

    def describe(self):
        return {"type": self.name, "horizon_taper": self.horizon_taper}


class PyUVDataJones(JonesBeam):
    """A pyuvdata E-field beam (``UVBeam`` file or object, or an analytic beam) through ``BeamInterface``.

    pyuvdata's feed ``feed_angle`` (0 north, pi/2 east) picks which of its feeds is mmflow's
    x (east) and y (north); a beam without feed angles takes feeds ``e``/``n`` by name, else
    its first two feeds as x, y. UVBeam values are interpolated by pyuvdata; its vector
    components are taken on its ``(az_hat, za_hat)`` basis, pyuvdata's only basis for E-field beams.

    Parameters
    ----------
    beam : pyuvdata.UVBeam, pyuvdata.analytic_beam.AnalyticBeam, or str (a file pyuvdata reads)
    """

    name = "pyuvdata_efield"

    def __init__(self, beam, lmax_hint=48):
        from pyuvdata import BeamInterface  # deferred: pyuvdata takes 2-3.5 s to import (docs/performance.md)

        self.source, beam = read_pyuvdata_beam(beam)
        if getattr(beam, "beam_type", "efield") != "efield":
            raise InputError(self.source, "beam_type", f"'{beam.beam_type}' beam",
                             "give an E-field beam (a power beam cannot describe Q, U, V)")
        self.interface = BeamInterface(beam, beam_type="efield")
        self.lmax_hint = lmax_hint
        self.feed_index = self._feed_order(beam)
        self.freq_range = beam_freq_range(self.interface)

    def _feed_order(self, beam):
        feeds = [str(f).lower() for f in np.atleast_1d(beam.feed_array)]
        angles = getattr(beam, "feed_angle", None)
        if len(feeds) < 2:
            raise InputError(self.source, "feed_array", f"feeds {feeds}", "give a beam with two crossed feeds")
        if angles is not None and len(np.atleast_1d(angles)) == len(feeds):
            ang = np.mod(np.atleast_1d(angles), np.pi)
            east = int(np.argmin(np.abs(ang - np.pi / 2)))
            north = int(np.argmin(np.minimum(ang, np.pi - ang)))
            if east != north:
                return (east, north)
        if "e" in feeds and "n" in feeds:
            return (feeds.index("e"), feeds.index("n"))
        return (0, 1)

    def _jones(self, az, za, freq_hz):
        az_uvb = (np.pi / 2 - az) % (2 * np.pi)  # pyuvdata: azimuth from east through north
        resp = self.interface.compute_response(az_array=az_uvb, za_array=za, freq_array=np.array([freq_hz]))
        resp = resp[:, list(self.feed_index), 0, :]  # (2 vec [az_hat, za_hat], 2 feeds, n)
        return np.stack([resp[1], resp[0]], axis=1)  # (feed, [theta, phi], n)

    def describe(self):
        return {"type": self.name, "source": self.source}


class JonesPowerBeam(Beam):
    """The Stokes-I power beam ``(|J_x|^2 + |J_y|^2) / 2`` of a :class:`JonesBeam`, for the scalar path;
    with ``feed`` one feed's ``|J_p|^2`` (the parallel hand pp of an unpolarised sky)."""

    name = "jones_power"

    def __init__(self, jones, feed=None):
        if feed not in (None,) + FEEDS:
            raise InputError("jones power beam", "feed", repr(feed), f"use one of {FEEDS} or None (Stokes I)")
        self.jones = jones
        self.feed = feed
        self.lmax_hint = jones.lmax_hint

    def check_frequency(self, freq_hz):
        self.jones.check_frequency(freq_hz)

    def _response(self, az, za, freq_hz):
        return self.jones.power(az, za, freq_hz, self.feed)

    def describe(self):
        out = {"type": self.name, "jones": self.jones.describe()}
        if self.feed is not None:
            out["feed"] = self.feed
        return out


def feed_telescopes(telescope):
    """The telescope as each feed sees an unpolarised sky, ``[x, y]`` (its beam :class:`JonesPowerBeam` of that
    feed), when its beam is a Jones beam's Stokes-I power beam (:class:`ShortDipoleJones`, :class:`PyUVDataJones`
    made into a scalar beam by :meth:`JonesBeam.power_beam`); None for any other beam (both feeds alike: a
    scalar beam, one feed's, or a pyuvdata beam read as a power beam)."""
    beam = telescope.beam
    if not isinstance(beam, JonesPowerBeam) or beam.feed is not None:
        return None
    return [dataclasses.replace(telescope, beam=JonesPowerBeam(beam.jones, feed)) for feed in FEEDS]
