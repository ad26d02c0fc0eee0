"""Antenna layouts: reading files, OVRO-LWA presets from the real stand positions.

Positions are local topocentric (east, north, up) metres from the array centre.
The OVRO-LWA files are shipped in ``mmflow/telescope/data`` with their provenance
(see ``PROVENANCE.md`` there).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from mmflow.errors import InputError

#: OVRO-LWA array centre LWA-000 (geodetic, deg) from ``ovro-lwa-352-antennas.txt``.
OVRO_LWA_CENTER = dict(lat_deg=37.23977727, lon_deg=-118.28166670)


@dataclass
class Layout:
    """A set of antennas with names and ENU positions.

    Attributes
    ----------
    names : list of str
    enu : ndarray, shape (n_ant, 3)
        East, north, up in metres relative to the array centre.
    lat_deg, lon_deg, height_m : float
        Geodetic site of the array centre.
    provenance : str
        Where the positions came from.
    """

    names: list
    enu: np.ndarray
    lat_deg: float
    lon_deg: float
    height_m: float = 0.0
    provenance: str = ""
    notes: list = field(default_factory=list)

    def __post_init__(self):
        self.enu = np.asarray(self.enu, dtype=np.float64).reshape(-1, 3)
        if len(self.names) != len(self.enu):
            raise InputError("layout", "names", f"{len(self.names)} names for {len(self.enu)} positions",
                             "give one name per antenna")
        if not np.all(np.isfinite(self.enu)):
            raise InputError("layout", "enu", "non-finite antenna position", "fix or drop that antenna")

    @property
    def n_ant(self):
        return len(self.names)

    def duplicates(self, tol_m=1e-3):
        """Duplicate antenna names and positions (closer than ``tol_m``) in words; '' when none.

        Two antennas at one position make a zero-length cross baseline that is really an
        autocorrelation; two with one name cannot be told apart in the data.
        """
        names, counts = np.unique(np.asarray(self.names, dtype=str), return_counts=True)
        words = []
        if np.any(counts > 1):
            words.append(f"duplicate names {[str(n) for n in names[counts > 1][:5]]}")
        if self.n_ant > 1:
            key = np.round(self.enu / tol_m).astype(np.int64)
            _, first, inverse, n = np.unique(key, axis=0, return_index=True, return_inverse=True,
                                             return_counts=True)
            same = [[self.names[i] for i in np.flatnonzero(inverse.ravel() == g)] for g in np.flatnonzero(n > 1)]
            if same:
                words.append(f"antennas at the same position {same[:5]}")
        return " and ".join(words)

    def select(self, mask_or_names=None, radius_m=None):
        """Return a sub-layout by boolean mask / index list / names and/or horizontal radius."""
        keep = np.ones(self.n_ant, bool)
        if mask_or_names is not None:
            sel = list(mask_or_names)
            if sel and isinstance(sel[0], str):
                unknown = sorted(set(sel) - set(self.names))
                if unknown:
                    raise InputError("layout", "stands", f"unknown stand names {unknown[:5]}",
                                     f"use names from the layout (e.g. {self.names[:3]})")
                keep &= np.isin(self.names, sel)
            else:
                arr = np.asarray(sel)
                m = np.zeros(self.n_ant, bool)
                if arr.dtype == bool:
                    m = arr
                else:
                    m[arr.astype(int)] = True
                keep &= m
        if radius_m is not None:
            keep &= np.hypot(self.enu[:, 0], self.enu[:, 1]) <= radius_m
        return Layout([n for n, k in zip(self.names, keep) if k], self.enu[keep], self.lat_deg,
                      self.lon_deg, self.height_m, self.provenance, list(self.notes))


def load_layout(path, lat_deg, lon_deg, height_m=0.0):
    """Read a whitespace text layout: ``name east north [up]`` per line, ``#`` comments.

    Parameters
    ----------
    path : str or Path
    lat_deg, lon_deg, height_m : float
        Site of the array centre.

    Raises
    ------
    InputError
        When a line has fewer than three columns or a non-numeric position.
    """
    path = Path(path)
    names, enu = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) < 3:
            raise InputError(f"{path}:{lineno}", "east/north", f"only {len(parts)} column(s) in '{s}'",
                             "write 'name east north [up]' in metres on every line")
        try:
            e, n = float(parts[1]), float(parts[2])
            u = float(parts[3]) if len(parts) > 3 else 0.0
        except ValueError:
            raise InputError(f"{path}:{lineno}", "east/north/up", f"non-numeric position in '{s}'",
                             "positions must be numbers in metres") from None
        names.append(parts[0])
        enu.append((e, n, u))
    if not names:
        raise InputError(str(path), "antennas", "no antenna lines found", "add 'name east north [up]' lines")
    layout = Layout(names, np.array(enu), lat_deg, lon_deg, height_m, provenance=str(path))
    dup = layout.duplicates()
    if dup:
        raise InputError(str(path), "antennas", dup, "give every antenna line a unique name and position")
    return layout


def _read_ovro_352():
    text = resources.files("mmflow.telescope.data").joinpath("ovro-lwa-352-antennas.txt").read_text()
    rows = []
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        p = line.split()
        if p[0] == "LWA-000":
            continue
        rows.append((p[0], p[1], p[4], float(p[5]), float(p[6]), p[7]))
    return rows


def ovro_lwa_layout(preset="core", radius_m=None, stands=None, max_antennas=None):
    """OVRO-LWA layouts from the real stand positions.

    Parameters
    ----------
    preset : {"core", "full", "paper-2017", "leda512-2013"}
        ``full``: the 352 stands used in the LWA-352 (from ``ovro-lwa-352-antennas.txt``);
        ``core``: stands LWA-001..LWA-251 (the ~200 m core);
        ``paper-2017``: an approximation of the reference paper's 256-antenna array: stands
        LWA-001..219 of the core, the five LEDA outriggers LWA-252..256 and the 32 fibre
        stands spread evenly in radius out to 800 m (longest baselines ~1.5 km);
        ``leda512-2013``: 256 stands of the 2013 as-built LEDA-512 survey (closest to the
        array of the reference paper, without its 32 expansion antennas).
    radius_m : float, optional
        Keep stands within this horizontal distance of the centre.
    stands : list of str, optional
        Keep only these stand names.
    max_antennas : int, optional
        Keep the first N stands (after the other cuts), for quick runs.

    Notes
    -----
    Heights in the 352-stand file are elevations above the ellipsoid and are missing
    ("N/A") for fibre stands: ``up`` is the elevation minus the median core elevation,
    and 0 where missing (recorded in ``Layout.notes``).
    """
    notes = []
    if preset in ("core", "full", "paper-2017"):
        rows = _read_ovro_352()
        elev = np.array([float(r[2]) if r[2] != "N/A" else np.nan for r in rows])
        ref = float(np.nanmedian(elev[:251]))
        missing = [r[0] for r, h in zip(rows, elev) if not np.isfinite(h)]
        if missing:
            notes.append(f"{len(missing)} stands without elevation: up=0 assumed")
        up = np.where(np.isfinite(elev), elev - ref, 0.0)
        num = np.array([int(r[0][4:]) for r in rows])
        if preset == "full":
            keep = [i for i, r in enumerate(rows) if r[5] == "YES"]
        elif preset == "core":
            keep = list(np.flatnonzero(num <= 251))
        else:
            fibre = [i for i, r in enumerate(rows) if r[1] == "Fiber" and r[5] == "YES"]
            fibre = sorted((i for i in fibre if np.hypot(rows[i][3], rows[i][4]) <= 800.0),
                           key=lambda i: np.hypot(rows[i][3], rows[i][4]))
            fibre = [fibre[k] for k in np.unique(np.linspace(0, len(fibre) - 1, 32).round().astype(int))]
            keep = sorted(list(np.flatnonzero(num <= 219)) + list(np.flatnonzero((num >= 252) & (num <= 256))) + fibre)
        lay = Layout([rows[i][0] for i in keep],
                     np.array([(rows[i][3], rows[i][4], up[i]) for i in keep]),
                     OVRO_LWA_CENTER["lat_deg"], OVRO_LWA_CENTER["lon_deg"], ref,
                     provenance="lwa-project/ovro_data_recorder ovro.txt @ d99cf6bb535f", notes=notes)
    elif preset == "leda512-2013":
        path = resources.files("mmflow.telescope.data").joinpath("ovro-lwa-leda512-2013-antennas.txt")
        with resources.as_file(path) as p:
            lay = load_layout(p, OVRO_LWA_CENTER["lat_deg"], OVRO_LWA_CENTER["lon_deg"], 1183.0)
        lay.provenance = "telegraphic/interfits antenna_locations.tpl @ 0ee46e94b84d (LEDA-512, 2013)"
    else:
        raise InputError("telescope", "preset", f"unknown OVRO-LWA preset '{preset}'",
                         "use one of 'core', 'full', 'paper-2017', 'leda512-2013'")
    lay = lay.select(stands, radius_m)
    if max_antennas is not None:
        lay = lay.select(np.arange(min(max_antennas, lay.n_ant)))
    return lay


def selected_layout(preset=None, layout_file=None, lat_deg=None, lon_deg=None, radius_m=None, stands=None,
                    max_antennas=None):
    """The array a run uses, and the layout it is selected from: ``(full, selected)``.

    An OVRO-LWA ``preset`` (cut by ``radius_m``, ``stands``, ``max_antennas``: :func:`ovro_lwa_layout`), or
    a text ``layout_file`` at (``lat_deg``, ``lon_deg``) cut by ``stands`` and ``radius_m``. The one place
    the telescope's stands are chosen: the configuration checks and the stages call it alike.
    """
    if layout_file is None:
        if preset is None:
            raise InputError("workflow", "telescope.layout_file", "no layout given",
                             "set telescope.preset, or layout_file with lat_deg and lon_deg")
        return (ovro_lwa_layout(preset),
                ovro_lwa_layout(preset, radius_m=radius_m, stands=stands, max_antennas=max_antennas))
    if lat_deg is None or lon_deg is None:
        raise InputError("workflow", "telescope.layout_file", "no layout given",
                         "set telescope.preset, or layout_file with lat_deg and lon_deg")
    full = load_layout(layout_file, lat_deg, lon_deg)
    return full, full.select(stands, radius_m)
