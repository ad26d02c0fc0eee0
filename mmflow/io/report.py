"""One HTML report per run: maps, PSFs, Table 1, flux scale, L-curves, CLEAN history, timings.

The report is a single HTML file with inline CSS and no JavaScript: it loads nothing from
the network and opens offline in any browser. Every text the run supplies is escaped
(:func:`html.escape`).

Images
------
``embed=False`` (the default) references each PNG by its path relative to the report
file. The report is written inside the run directory (``<run>/report.html``) and every image
is a product inside that directory, so the links survive moving or copying the whole run
folder, and the PNGs are not stored twice (the paper's 22 channels with map, residual, PSF and
L-curve figures would add ~20 MB of base64 to the page). ``embed=True`` writes the PNGs into
the page as ``data:image/png;base64`` URIs instead: one file that can be mailed on its own.
FITS, CSV and JSON products are always linked relatively (they cannot be shown inline).

Paths in the summary are relative to the run directory; absolute paths and paths that leave
it (``..``) are refused, since they would break when the run folder moves.

:func:`check_report` is the pure-Python check of a written report (every ``<img>`` resolves to
a PNG that decodes with a nonzero size, no external resource, balanced tags).
"""
from __future__ import annotations

import base64
import html
import io
import json
import os
from dataclasses import asdict, dataclass, field, fields
from datetime import datetime, timedelta, timezone
from html.parser import HTMLParser
from pathlib import Path, PurePosixPath

from PIL import Image  # Pillow: a dependency of matplotlib, loaded with it

from mmflow.analysis.table1 import split_columns
from mmflow.errors import InputError


# ----------------------------------------------------------------------------- summary schema

@dataclass
class Figure:
    """A PNG (path relative to the run directory) and its caption."""

    path: str
    caption: str = ""


@dataclass
class ChannelProducts:
    """What one frequency channel produced.

    Attributes
    ----------
    freq_hz : float
    images : list of Figure
        The channel's pictures in display order: Mollweide maps (restored, dirty, residual,
        model), PSF stamps, the L-curve.
    files : dict label -> path
        Downloadable products (FITS maps, PSF stamps, summaries), relative to the run dir.
    info : dict
        Scalar facts shown as a two-column table (the products stage's per-channel info:
        resolution_deg, map_rms, unit, lcurve_corner_eps, ...). Nested values are shown as JSON.
    """

    freq_hz: float
    images: list = field(default_factory=list)
    files: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


@dataclass
class ReportSummary:
    """Everything :func:`write_report` shows; every path is relative to the run directory.

    Attributes
    ----------
    title : str
    run_name : str
    created : str
        ISO time stamp (default: now, UTC).
    versions : dict package -> version (the run's ``run.json``).
    cluster : dict
        What the run ran on (the run's ``run.json``): ``kind`` (``local``, ``slurm``, ``pbs``, ``address``,
        ``synchronous``) and the shape it was given (``workers``, ``threads_per_worker``, ``memory_limit``;
        ``jobs`` and their ``job`` options).
    channels : list of ChannelProducts, one per frequency.
    table1 : list of dict
        Rows of :func:`mmflow.analysis.table1.table1_row` (keys ``freq_mhz``,
        ``bandwidth_mhz``, ``fwhm_major_arcmin_dec+45``, ..., ``noise_k``,
        ``noise_mjy_per_beam``, ``fraction_of_modes``).
    table1_files : dict label -> path (e.g. ``{"CSV": "table1.csv"}``).
    flux_scale : list of dict
        Rows of :func:`mmflow.analysis.fluxscale.flux_scale_rows` (``name``, ``freq_hz``,
        ``measured_jy``, ``model_jy``, ``ratio``, ``reference``).
    flux_scale_figure : Figure or None (:func:`mmflow.io.plots.write_flux_scale_png`).
    flux_scale_files : dict label -> path (the flux-scale CSV and JSON).
    astrometry : list of dict
        Rows of :func:`mmflow.analysis.astrometry.registration_rows`.
    astrometry_fit : dict
        The global fit (``rotation_arcmin``, ``axis``, ``rms_before_arcmin``, ...).
    spectral_index : list of Figure
        Three-colour and beta / R^2 Mollweides (:mod:`mmflow.io.plots`).
    spectral_index_files : dict label -> path (the beta and R^2 FITS maps).
    clean_history : dict channel label -> list of dict
        One row per major cycle (e.g. ``cycle``, ``peak``, ``components``, ``seconds``), the
        stop reason as a row key or in ``clean_stop``.
    clean_stop : dict channel label -> str (why CLEAN stopped).
    clean_figures : list of Figure (e.g. peak against cycle).
    stage_times : list of dict
        One row per stage of the run's ``summary.json`` (``stage``, ``wall_s``, ``tasks``,
        ``tasks_run``, ``task_s``, ...); ``wall_s`` is drawn as a bar.
    figures : list of Figure, anything else worth showing.
    notes : list of str, shown at the top (warnings, provenance).
    """

    title: str = "mmflow run report"
    run_name: str = ""
    created: str = ""
    versions: dict = field(default_factory=dict)
    cluster: dict = field(default_factory=dict)
    channels: list = field(default_factory=list)
    table1: list = field(default_factory=list)
    table1_files: dict = field(default_factory=dict)
    flux_scale: list = field(default_factory=list)
    flux_scale_figure: Figure | None = None
    flux_scale_files: dict = field(default_factory=dict)
    astrometry: list = field(default_factory=list)
    astrometry_fit: dict = field(default_factory=dict)
    spectral_index: list = field(default_factory=list)
    spectral_index_files: dict = field(default_factory=dict)
    clean_history: dict = field(default_factory=dict)
    clean_stop: dict = field(default_factory=dict)
    clean_figures: list = field(default_factory=list)
    stage_times: list = field(default_factory=list)
    figures: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    def to_json(self):
        return json.dumps(asdict(self), indent=1)

    @classmethod
    def from_dict(cls, d):
        """Inverse of ``asdict`` (figures and channels from plain dicts, unknown keys refused)."""
        known = {f.name for f in fields(cls)}
        extra = set(d) - known
        if extra:
            raise InputError("report summary", sorted(extra)[0], "unknown key",
                             f"use only the fields of ReportSummary: {sorted(known)}")
        d = dict(d)
        fig = lambda x: x if isinstance(x, Figure) else Figure(**x)  # noqa: E731
        for k in ("spectral_index", "clean_figures", "figures"):
            d[k] = [fig(x) for x in d.get(k, [])]
        if d.get("flux_scale_figure") is not None:
            d["flux_scale_figure"] = fig(d["flux_scale_figure"])
        d["channels"] = [c if isinstance(c, ChannelProducts) else
                         ChannelProducts(**{**c, "images": [fig(x) for x in c.get("images", [])]})
                         for c in d.get("channels", [])]
        return cls(**d)


#: the stage table's columns (peak resident memory of the workers and the driver in GB)
STAGE_COLUMNS = ("wall_s", "tasks", "tasks_run", "task_s", "worker_peak_rss_gb", "driver_peak_rss_gb")


def summary_from_run(run_dir):
    """A :class:`ReportSummary` of everything a run recorded.

    Reads ``run.json`` (name, versions), ``summary.json`` (per-stage ``wall_s``, tasks) and
    ``maps/summary.json``: per channel the map, its L-curve ``maps/lcurve_<tag>.png`` when
    present, the CLEAN images (restored, residual, model, noise) and PSF stamps with their
    FITS files, the CLEAN history and stop reason; for the run Table 1, the flux scale,
    astrometry, spectral-index products and the CLEAN history figure, as the products stage
    writes them (:mod:`mmflow.workflow.stages.products.science`).
    """
    run = Path(run_dir)
    s = ReportSummary()
    meta = _read_json(run / "run.json") or {}
    s.run_name, s.versions = meta.get("name", run.name) or run.name, meta.get("versions", {})
    s.cluster = meta.get("cluster") or {}
    top = _read_json(run / "maps" / "summary.json") or {}
    stages = top.get("stages") or _read_json(run / "summary.json") or {}  # the products stage's copy, or the run's
    for name, st in stages.items():  # the products stage's row counts up to the report (its "until")
        label = f"{name} (until {st['until']})" if st.get("until") else name
        s.stage_times.append({"stage": label, **{k: st.get(k) for k in STAGE_COLUMNS}})
    for info in top.get("maps", []):
        s.channels.append(_channel(run, info, s))
    t1 = top.get("table1") or {}
    s.table1 = t1.get("rows", [])
    s.table1_files = {PurePosixPath(f).suffix.lstrip(".").upper() or f: f for f in t1.get("files", [])}
    fs = top.get("flux_scale") or {}
    s.flux_scale, s.flux_scale_files = fs.get("rows", []), fs.get("files", {})
    if fs.get("figure"):
        s.flux_scale_figure = Figure(fs["figure"], "measured fluxes over the published spectra (flux scale)")
    astro = top.get("astrometry") or {}
    s.astrometry = astro.get("rows", [])
    s.astrometry_fit = astro.get("fit", {})
    si = top.get("spectral_index") or {}
    s.spectral_index = [Figure(**f) for f in si.get("figures", [])]
    s.spectral_index_files = si.get("files", {})
    if top.get("clean_figure"):
        s.clean_figures.append(Figure(top["clean_figure"], "CLEAN: residual peak and components per major cycle"))
    return s


_CLEAN_IMAGES = ("restored", "residual", "model", "noise", "daynight")


def _channel(run, info, s):
    """One channel's :class:`ChannelProducts` (and its CLEAN history into ``s``)."""
    ch = ChannelProducts(float(info["freq_hz"]))
    facts = dict(info)
    mhz = f"{ch.freq_hz / 1e6:.3f} MHz"
    if facts.get("png"):
        ch.images.append(Figure(facts.pop("png"), f"map at {mhz}"))
        lc = facts["fits"].replace("map_", "lcurve_").replace(".fits", ".png") if facts.get("fits") else None
        if lc and (run / lc).is_file():
            ch.images.append(Figure(lc, "L-curve"))
    if facts.get("fits"):
        ch.files["map (FITS)"] = facts.pop("fits")
    for name, img in (facts.pop("images", None) or {}).items():
        if img.get("png"):
            ch.images.append(Figure(img["png"], _image_caption(name, mhz, facts.get("noise") or {})))
        if img.get("fits"):
            ch.files[f"{name} (FITS)"] = img["fits"]
    stamps = facts.pop("psf_stamps", None) or []
    for st in stamps:
        ch.files[f"PSF dec {st['dec_deg']:+.0f} (FITS)"] = st["fits"]
    pngs = list(dict.fromkeys(st["png"] for st in stamps if st.get("png")))
    ch.images += [Figure(p, f"PSF at {mhz}, dec 0, +45, +75") for p in pngs]
    clean = facts.pop("clean", None)
    if clean:
        label = mhz
        hist = clean.get("history", {})
        s.clean_history[label] = [{"cycle": c, "peak_jy_per_sr": pk, "components": n} for c, (pk, n) in
                                  enumerate(zip(hist.get("peak_jy_per_sr", []), hist.get("components", [])))]
        s.clean_stop[label] = str(clean.get("stop"))
        facts["clean"] = {k: v for k, v in clean.items() if k != "history"}
    for k in ("flux_scale", "astrometry", "table1"):  # shown in their own sections
        facts.pop(k, None)
    ch.info = facts
    return ch


def _image_caption(name, mhz, noise):
    """The caption of one CLEAN image; the day/night map's says its rms beside the jackknife sigma."""
    dn = (noise.get("by_split") or {}).get("day_night")
    if name != "daynight" or not dn:
        return f"CLEAN {name} at {mhz}"
    return (f"day/night systematics sqrt(f_d f_n) (day - night) at {mhz}: rms {dn['kelvin']:.3g} K over the seen "
            f"sky, jackknife noise {noise.get('kelvin', float('nan')):.3g} K (a systematics check, not a noise "
            "estimate: noise alone gives about the jackknife sigma, whatever the day and night shares f_d, f_n)")


def _read_json(path):
    return json.loads(path.read_text()) if path.is_file() else None


# ----------------------------------------------------------------------------- writing

_CSS = """
body{font-family:sans-serif;margin:1.5em auto;max-width:1200px;color:#222;line-height:1.35}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .5em;text-align:right}th{background:#f0f0f0}
td.l,th.l{text-align:left}figure{display:inline-block;margin:.5em;vertical-align:top;max-width:100%}
figure img{max-width:100%;height:auto;border:1px solid #ddd}figcaption{font-size:.85em;color:#555}
.bar{background:#4a7ab5;height:.8em;display:inline-block}.missing{color:#b00;font-weight:bold}
nav a{margin-right:1em}.note{background:#fff6d5;padding:.4em .6em;border-left:4px solid #e0b000}
"""


def _esc(x):
    return html.escape(str(x), quote=True)


#: Julian date 2451545.0 is 2000-01-01 12:00 (a run's epochs are UTC Julian dates)
_J2000 = (2451545.0, datetime(2000, 1, 1, 12, tzinfo=timezone.utc))


def jd_text(jd):
    """A Julian date in full and as a UTC date: ``'2458000.50000 (2017-09-04 00:00:00 UTC)'``."""
    when = _J2000[1] + timedelta(days=float(jd) - _J2000[0])
    return f"{float(jd):.5f} ({when:%Y-%m-%d %H:%M:%S} UTC)"


def mhz_text(hz):
    """A frequency in MHz with three decimals, more where the channel needs them: ``'40.000 MHz'``."""
    mhz = float(hz) / 1e6
    text = f"{mhz:.3f}"
    if abs(float(text) - mhz) > 1e-9 * max(abs(mhz), 1.0):
        text = f"{mhz:.9f}".rstrip("0")
    return f"{text} MHz"


def _fmt(v, key=""):
    """A value as the report prints it; ``key`` (the value's name) picks dates (``*_jd``) and frequencies
    (``*_hz``), which a 4-digit float would hide (``2.458e+06``, ``4e+07``)."""
    if isinstance(v, bool) or v is None:
        return "" if v is None else str(v)
    if isinstance(v, (int, float)) and str(key).endswith("_jd"):
        return jd_text(v)
    if isinstance(v, (int, float)) and str(key).endswith("_hz"):
        return mhz_text(v)
    if isinstance(v, float):
        return f"{v:.6g}" if 1e4 <= abs(v) < 1e6 else f"{v:.4g}"
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(v)
    return str(v)


def cluster_text(c):
    """What a run ran on, in words (:attr:`ReportSummary.cluster`); empty where the run did not record it."""
    kind = c.get("kind")
    if not kind:
        return ""
    if kind == "synchronous":
        return "in one process (dask's synchronous scheduler)"
    if kind == "address":
        return "on a dask cluster joined by its address"
    def count(n, word):
        return f"{n} {word}" + ("" if n == 1 else "s")

    if kind == "local":
        return (f"on a local cluster: {count(c.get('workers'), 'worker')} of "
                f"{count(c.get('threads_per_worker'), 'thread')}, memory limit {c.get('memory_limit')} each")
    job = ", ".join(f"{k} {v}" for k, v in (c.get("job") or {}).items())
    return f"on a {kind.upper()} cluster: {count(c.get('jobs'), 'job')}" + (f" ({job})" if job else "")


class _Writer:
    def __init__(self, report_path, run_dir, embed):
        self.dir = Path(report_path).resolve().parent
        self.run = Path(run_dir).resolve()
        self.embed = embed
        self.missing = []

    def _resolve(self, rel, what):
        p = PurePosixPath(str(rel).replace(os.sep, "/"))
        if p.is_absolute() or ".." in p.parts or Path(str(rel)).is_absolute():
            raise InputError("report summary", what, f"path '{rel}' is not inside the run directory",
                             "give paths relative to the run directory (e.g. maps/map_40.000MHz.png)")
        return self.run / p

    def href(self, rel, what):
        target = self._resolve(rel, what)
        return Path(os.path.relpath(target, self.dir)).as_posix(), target

    def figure(self, fig):
        src, target = self.href(fig.path, "figure path")
        cap = f"<figcaption>{_esc(fig.caption)}</figcaption>" if fig.caption else ""
        if not target.is_file():
            self.missing.append(fig.path)
            return f'<figure><p class="missing">missing image: {_esc(fig.path)}</p>{cap}</figure>'
        if self.embed:
            src = "data:image/png;base64," + base64.b64encode(target.read_bytes()).decode("ascii")
        return f'<figure><img src="{_esc(src)}" alt="{_esc(fig.caption or fig.path)}">{cap}</figure>'

    def links(self, files):
        out = []
        for label, rel in files.items():
            href, target = self.href(rel, f"file '{label}'")
            if target.exists():
                out.append(f'<a href="{_esc(href)}">{_esc(label)}</a>')
            else:
                self.missing.append(rel)
                out.append(f'<span class="missing">{_esc(label)} missing ({_esc(rel)})</span>')
        return " | ".join(out)


def _table(rows, columns=None, left=("name", "stage", "reference", "key", "label", "reason", "method")):
    if not rows:
        return "<p>none</p>"
    columns = columns or list(dict.fromkeys(k for r in rows for k in r))
    cls = lambda c: ' class="l"' if c in left else ""  # noqa: E731
    head = "".join(f"<th{cls(c)}>{_esc(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td{cls(c)}>{_esc(_fmt(r.get(c), c))}</td>" for c in columns) + "</tr>"
                   for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _facts(d):
    rows = "".join(f'<tr><th class="l">{_esc(k)}</th><td class="l">{_esc(_fmt(v, k))}</td></tr>' for k, v in d.items())
    return f"<table>{rows}</table>" if rows else ""


def table1_html(rows):
    """Table 1 as the paper lays it out (FWHM as ``major' x minor'`` per declination), then the
    noise of each jackknife the splits allow and the day/night rms
    (:func:`mmflow.analysis.table1.split_columns`)."""
    if not rows:
        return "<p>none</p>"
    decs = [k[len("fwhm_major_arcmin_dec"):] for k in rows[0] if k.startswith("fwhm_major_arcmin_dec")]
    head = ["#", "&nu; (MHz)", "&Delta;&nu; (MHz)"] + [f"FWHM at &delta; = {_esc(d)}&deg;" for d in decs] + \
        ["noise (K)", "noise (mJy/beam)", "fraction &sigma; &gt; &radic;&epsilon;"] + \
        [f"{_esc(label)} {u}" for _, label in split_columns(rows) for u in ("(K)", "(mJy/beam)")]
    out = ["<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for i, r in enumerate(rows, 1):
        cells = [str(i), f"{r['freq_mhz']:.3f}", f"{r['bandwidth_mhz']:.3f}"]
        cells += [f"{r['fwhm_major_arcmin_dec' + d]:.1f}&prime; &times; {r['fwhm_minor_arcmin_dec' + d]:.1f}&prime;"
                  for d in decs]
        cells += [f"{r['noise_k']:.0f}", f"{r['noise_mjy_per_beam']:.0f}", f"{r['fraction_of_modes']:.3f}"]
        cells += [f"{r[f'noise_{u}_{k}']:.0f}" for k, _ in split_columns(rows) for u in ("k", "mjy_per_beam")]
        out.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    return "".join(out) + "</table>"


def _timings(rows):
    if not rows:
        return "<p>none</p>"
    top = max(float(r.get("wall_s") or 0) for r in rows) or 1.0
    cols = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f'<th{" class=l" if c == "stage" else ""}>{_esc(c)}</th>' for c in cols) + '<th class="l"></th>'
    body = ""
    for r in rows:
        w = 200.0 * float(r.get("wall_s") or 0) / top
        body += "<tr>" + "".join(f'<td{" class=l" if c == "stage" else ""}>{_esc(_fmt(r.get(c), c))}</td>'
                                 for c in cols)
        body += f'<td class="l"><span class="bar" style="width:{w:.0f}px"></span></td></tr>'
    total = sum(float(r.get("wall_s") or 0) for r in rows)
    return f"<table><tr>{head}</tr>{body}</table><p>total wall time {total:.1f} s</p>"


def render_report(summary, report_path, run_dir=None, embed=False):
    """The report's HTML text and the summary paths whose files are missing."""
    s = summary if isinstance(summary, ReportSummary) else ReportSummary.from_dict(summary)
    w = _Writer(report_path, run_dir if run_dir is not None else Path(report_path).parent, embed)
    created = s.created or datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    sections = []

    def section(anchor, title, body):
        sections.append((anchor, title, f'<h2 id="{anchor}">{_esc(title)}</h2>{body}'))

    if s.table1:
        links = w.links(s.table1_files)
        section("table1", "Table 1: channel summary", table1_html(s.table1) + (f"<p>{links}</p>" if links else ""))
    for i, ch in enumerate(s.channels):
        body = "".join(w.figure(f) for f in ch.images) + _facts(ch.info)
        links = w.links(ch.files)
        section(f"ch{i}", f"Channel {ch.freq_hz / 1e6:.3f} MHz", body + (f"<p>{links}</p>" if links else ""))
    if s.flux_scale or s.flux_scale_figure:
        cols = ["name", "freq_hz", "measured_jy", "model_jy", "ratio", "reference"]
        cols[4:4] = [c for c in ("measured_err_jy", "clean_jy", "method", "fwhm_arcmin")
                     if any(c in r for r in s.flux_scale)]
        body = (w.figure(s.flux_scale_figure) if s.flux_scale_figure else "") + _table(s.flux_scale, cols)
        links = w.links(s.flux_scale_files)
        section("fluxscale", "Flux scale", body + (f"<p>{links}</p>" if links else ""))
    if s.astrometry or s.astrometry_fit:
        section("astrometry", "Astrometric registration", _facts(s.astrometry_fit) + _table(s.astrometry))
    if s.spectral_index or s.spectral_index_files:
        links = w.links(s.spectral_index_files)
        section("spectral", "Spectral index", "".join(w.figure(f) for f in s.spectral_index)
                + (f"<p>{links}</p>" if links else ""))
    if s.clean_history or s.clean_figures:
        body = "".join(w.figure(f) for f in s.clean_figures)
        for label, rows in s.clean_history.items():
            stop = s.clean_stop.get(label)
            body += f"<h3>{_esc(label)}</h3>" + (f"<p>stopped: {_esc(stop)}</p>" if stop else "") + _table(rows)
        section("clean", "CLEAN cycle history", body)
    if s.stage_times:
        section("timings", "Stage timings", _timings(s.stage_times))
    if s.figures:
        section("figures", "Other figures", "".join(w.figure(f) for f in s.figures))
    if s.versions:
        section("versions", "Software versions", _facts(s.versions))
    notes = "".join(f'<p class="note">{_esc(n)}</p>' for n in s.notes)
    if w.missing:
        notes += f'<p class="note missing">{len(w.missing)} product file(s) missing: ' \
                 f'{_esc(", ".join(w.missing))}</p>'
    nav = " ".join(f'<a href="#{a}">{_esc(t)}</a>' for a, t, _ in sections)
    page = (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{_esc(s.title)}</title><style>{_CSS}</style></head><body>"
            f"<h1>{_esc(s.title)}</h1><p>run <b>{_esc(s.run_name)}</b>"
            + (f' <span id="cluster">{_esc(cluster_text(s.cluster))}</span>' if s.cluster else "")
            + f", report written {_esc(created)}</p>"
            f"{notes}<nav>{nav}</nav>" + "".join(body for _, _, body in sections) + "</body></html>\n")
    return page, w.missing


def write_report(path, summary, run_dir=None, embed=False):
    """Write the run's HTML report (atomically: a temporary name, then renamed).

    Parameters
    ----------
    path : str or Path
        The report file, normally ``<run>/report.html``.
    summary : ReportSummary or dict (``asdict`` form, e.g. read back from JSON)
    run_dir : str or Path
        The directory the summary's paths are relative to (default: ``path``'s folder).
    embed : bool
        Embed the PNGs as data URIs (one self-sufficient file) instead of relative links.

    Returns
    -------
    list of str
        Summary paths whose files do not exist (shown in red in the report).
    """
    path = Path(path)
    page, missing = render_report(summary, path, run_dir, embed)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(page, encoding="utf-8")
    os.replace(tmp, path)
    return missing


# ----------------------------------------------------------------------------- checking

_VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}


class _Scan(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.imgs, self.refs, self.stack, self.problems = [], [], [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a.get("src") or "")
        for key in ("src", "href"):
            if a.get(key):
                self.refs.append((tag, a[key]))
        if tag not in _VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in _VOID:
            self.stack.pop()

    def handle_endtag(self, tag):
        if tag in _VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.problems.append(f"unbalanced </{tag}> (open: {self.stack[-3:]})")
            if tag in self.stack:
                while self.stack.pop() != tag:
                    pass
        else:
            self.stack.pop()


def png_size(data):
    """``(width, height)`` of PNG bytes after a full decode (Pillow); raises ValueError if not a PNG."""
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        raise ValueError("not a PNG (bad signature)")
    with Image.open(io.BytesIO(data)) as im:
        im.load()
        return im.size


def check_report(path):
    """Problems with a written report (empty list: fine).

    Every ``<img>`` must be a ``data:image/png;base64`` URI or a relative path to a file inside
    the report's folder tree or beside it, and decode as a PNG of nonzero width and height;
    no ``src``/``href`` may point off the machine (``http:``, ``//``); the tags must balance.
    Links to other files (``<a href>``) must resolve to existing files.
    """
    path = Path(path)
    scan = _Scan()
    scan.feed(path.read_text(encoding="utf-8"))
    scan.close()
    problems = list(scan.problems) + [f"unclosed <{t}>" for t in scan.stack]
    if not scan.imgs:
        problems.append("no <img> in the report")
    external = ("http:", "https:", "//", "ftp:", "file:")
    for tag, ref in scan.refs:
        low = ref.strip().lower()
        if low.startswith(external):
            problems.append(f"<{tag}> refers outside the run: {ref[:80]}")
        elif tag == "a" and not low.startswith(("#", "data:")) and not (path.parent / ref).exists():
            problems.append(f"link to a missing file: {ref}")
    for src in scan.imgs:
        label = src[:60]
        if src.strip().lower().startswith(external):
            continue
        try:
            if src.startswith("data:"):
                head, _, payload = src.partition(",")
                if head != "data:image/png;base64":
                    raise ValueError(f"unsupported data URI '{head}'")
                data = base64.b64decode(payload, validate=True)
            else:
                f = path.parent / src
                if not f.is_file():
                    raise ValueError("file not found")
                data = f.read_bytes()
            wdt, hgt = png_size(data)
            if wdt <= 0 or hgt <= 0:
                raise ValueError(f"empty image {wdt}x{hgt}")
        except Exception as exc:  # noqa: BLE001 - every failure is a finding
            problems.append(f"<img src={label!r}>: {exc}")
    return problems
