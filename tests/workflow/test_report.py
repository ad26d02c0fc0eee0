"""The per-run HTML report: every image loads (pure-Python decode and headless Chromium),
nothing is fetched from outside, text is escaped, links survive moving the run folder."""
import json
import shutil
from dataclasses import asdict

import healpy
import numpy as np
import pytest

from mmflow.io.report import ChannelProducts, Figure, ReportSummary, check_report, summary_from_run, write_report

from tests.headless_chromium import Chromium, find_chromium

HOSTILE = '<script>console.error("injected")</script><img src="http://example.invalid/x.png">'


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A run folder as the products stage leaves it, with real PNGs from mmflow's writers."""
    from mmflow.io.export import write_lcurve_png, write_mollweide_png
    from mmflow.io.plots import write_clean_history_png, write_flux_scale_png, write_three_colour_png

    run = tmp_path_factory.mktemp("run") / "myrun"
    (run / "maps").mkdir(parents=True)
    nside = 16
    x, y, z = healpy.pix2vec(nside, np.arange(healpy.nside2npix(nside)))
    sky = 1e3 * (1 + 0.3 * z + 0.2 * x)
    mask = z > -0.6
    channels = []
    for f in (40e6, 60e6):
        tag = f"{f / 1e6:.3f}MHz"
        write_mollweide_png(run / "maps" / f"map_{tag}.png", sky * (f / 40e6) ** -2.5, tag, "K", mask=mask, lmax=32,
                            eps=1e-2, freq_hz=f, frame="icrs", xsize=200)
        eps = np.logspace(-4, 0, 9)
        lc = np.stack([1 / (eps + 1e-3), eps + 1e-2], axis=1)
        write_lcurve_png(run / "maps" / f"lcurve_{tag}.png", lc, eps, 1e-2, freq_hz=f)
        (run / "maps" / f"map_{tag}.fits").write_bytes(b"SIMPLE  =                    T")
        info = {"freq_hz": f, "fits": f"maps/map_{tag}.fits", "png": f"maps/map_{tag}.png", "nside": nside,
                "unit": "K", "resolution_deg": 5.6, "map_rms": 123.4, "lcurve_corner_eps": 0.01}
        (run / "maps" / f"summary_{tag}.json").write_text(json.dumps(info))
        channels.append(info)
    (run / "maps" / "summary.json").write_text(json.dumps({"maps": channels}))
    (run / "run.json").write_text(json.dumps({"name": "myrun", "versions": {"mmflow": "0.1.0", "numpy": "2"}}))
    (run / "summary.json").write_text(json.dumps({
        "mmodes": {"stage": "mmodes", "wall_s": 12.5, "tasks": 4, "tasks_run": 4, "task_s": 20.1},
        "products": {"stage": "products", "wall_s": 3.0, "tasks": 2, "tasks_run": 2, "task_s": 2.9}}))
    rows = [{"name": n, "freq_hz": f, "measured_jy": s, "model_jy": s, "ratio": 1.0, "reference": "test"}
            for n, s0 in (("3C 286", 30.0), ("Cyg A", 20000.0)) for f, s in ((40e6, s0), (60e6, 0.8 * s0))]
    write_flux_scale_png(run / "fluxscale.png", rows)
    write_clean_history_png(run / "clean_history.png", {"40.000MHz": [{"peak": 10.0 / (c + 1), "components": 50}
                                                                      for c in range(5)]})
    write_three_colour_png(run / "three_colour.png", [sky, sky * 0.4, sky * 0.2], [40e6, 60e6, 80e6], mask=mask,
                           xsize=200)
    return run


def _summary(run):
    s = summary_from_run(run)
    s.title = "Report of " + HOSTILE
    s.notes = ["a note with <b>markup</b> & an ampersand"]
    s.table1 = [{"freq_mhz": 40.0, "bandwidth_mhz": 0.024, "fwhm_major_arcmin_dec+0": 20.0,
                 "fwhm_minor_arcmin_dec+0": 16.0, "fwhm_major_arcmin_dec+45": 16.8, "fwhm_minor_arcmin_dec+45": 14.6,
                 "noise_k": 900.0, "noise_mjy_per_beam": 800.0, "fraction_of_modes": 0.512}]
    s.flux_scale = [{"name": "3C 286", "freq_hz": 40e6, "measured_jy": 30.0, "model_jy": 29.0, "ratio": 1.03,
                     "reference": HOSTILE}]
    s.flux_scale_figure = Figure("fluxscale.png", "flux scale")
    s.spectral_index = [Figure("three_colour.png", "three colours")]
    s.clean_history = {"40.000MHz": [{"cycle": c, "peak": 10.0 / (c + 1), "components": 50} for c in range(5)]}
    s.clean_stop = {"40.000MHz": "threshold"}
    s.clean_figures = [Figure("clean_history.png", "CLEAN history")]
    s.astrometry_fit = {"rotation_arcmin": 1.2, "rms_before_arcmin": 3.0, "rms_after_arcmin": 0.4}
    return s


def test_summary_from_run_reads_what_a_run_records(run_dir):
    s = summary_from_run(run_dir)
    assert s.run_name == "myrun" and s.versions["mmflow"] == "0.1.0"
    assert [c.freq_hz for c in s.channels] == [40e6, 60e6]
    assert [f.path for f in s.channels[0].images] == ["maps/map_40.000MHz.png", "maps/lcurve_40.000MHz.png"]
    assert s.channels[1].files == {"map (FITS)": "maps/map_60.000MHz.fits"}
    assert s.channels[0].info["map_rms"] == 123.4 and "png" not in s.channels[0].info
    assert [(r["stage"], r["wall_s"]) for r in s.stage_times] == [("mmodes", 12.5), ("products", 3.0)]
    back = ReportSummary.from_dict(json.loads(s.to_json()))
    assert asdict(back) == asdict(s)
    with pytest.raises(ValueError, match="unknown key"):
        ReportSummary.from_dict({"chanels": []})


@pytest.mark.parametrize("embed", [False, True])
def test_report_images_decode_and_links_survive_a_move(run_dir, tmp_path, embed):
    report = run_dir / f"report_{int(embed)}.html"
    assert write_report(report, _summary(run_dir), embed=embed) == []
    assert check_report(report) == []
    text = report.read_text()
    # every image of the run is in the page; text is escaped (no element injected)
    n_img = text.count("<img ")
    assert n_img == 2 * 2 + 3
    assert "<script" not in text and '="http' not in text and "&lt;script&gt;" in text
    assert "16.8&prime; &times; 14.6&prime;" in text and "0.512" in text
    assert ("data:image/png;base64," in text) == embed
    # move the whole run folder: the report still resolves everything
    moved = shutil.move(str(run_dir), str(tmp_path / "elsewhere"))
    try:
        assert check_report(tmp_path / "elsewhere" / report.name) == []
        if embed:  # the embedded report shows every image on its own (only the FITS links need the run)
            alone = shutil.copy(tmp_path / "elsewhere" / report.name, tmp_path / "alone.html")
            assert sorted(check_report(alone)) == [f"link to a missing file: maps/map_{t}.fits"
                                                   for t in ("40.000MHz", "60.000MHz")]
    finally:
        shutil.move(moved, str(run_dir))


def test_check_report_finds_broken_images_and_external_resources(run_dir, tmp_path):
    bad = tmp_path / "bad.html"
    png = (run_dir / "fluxscale.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(png[: len(png) // 2])
    (tmp_path / "ok.png").write_bytes(png)
    bad.write_text('<html><body><img src="ok.png"><img src="cut.png"><img src="gone.png">'
                   '<img src="data:image/png;base64,AAAA"><img src="https://cdn.invalid/a.png">'
                   '<link rel="stylesheet" href="//cdn.invalid/x.css"><a href="nothing.fits">x</a><div></body></html>')
    problems = check_report(bad)
    text = "\n".join(problems)
    assert "ok.png" not in text and len(problems) == 7
    for needle in ("cut.png", "gone.png", "data:image/png;base64,AAAA", "https://cdn.invalid", "//cdn.invalid/x.css",
                   "nothing.fits", "unbalanced </body>"):
        assert needle in text, (needle, problems)


def test_report_refuses_paths_outside_the_run_and_flags_missing_files(run_dir, tmp_path):
    s = ReportSummary(channels=[ChannelProducts(40e6, images=[Figure("/etc/hostname")])])
    with pytest.raises(ValueError, match="not inside the run directory"):
        write_report(run_dir / "r.html", s)
    s = ReportSummary(figures=[Figure("../outside.png")])
    with pytest.raises(ValueError, match="not inside the run directory"):
        write_report(run_dir / "r.html", s)
    s = ReportSummary(figures=[Figure("maps/map_40.000MHz.png"), Figure("maps/nothing.png")],
                      channels=[ChannelProducts(40e6, files={"FITS": "maps/nothing.fits"})])
    missing = write_report(run_dir / "r_missing.html", s)
    assert missing == ["maps/nothing.fits", "maps/nothing.png"] or sorted(missing) == ["maps/nothing.fits",
                                                                                       "maps/nothing.png"]
    text = (run_dir / "r_missing.html").read_text()
    assert "missing image: maps/nothing.png" in text and "2 product file(s) missing" in text


def test_report_in_a_subfolder_links_back_into_the_run(run_dir):
    (run_dir / "report").mkdir(exist_ok=True)
    out = run_dir / "report" / "index.html"
    write_report(out, _summary(run_dir), run_dir=run_dir)
    assert 'src="../maps/map_40.000MHz.png"' in out.read_text()
    assert check_report(out) == []


@pytest.mark.parametrize("embed", [False, True])
def test_report_renders_in_headless_chromium(run_dir, tmp_path, embed):
    exe = find_chromium()
    if exe is None:
        pytest.skip("no Chromium binary (install Debian's `chromium` package, or set MMFLOW_CHROMIUM); "
                    "the pure-Python image checks above still ran")
    report = run_dir / f"report_browser_{int(embed)}.html"
    write_report(report, _summary(run_dir), embed=embed)
    with Chromium(exe) as browser:
        browser.open(report.resolve().as_uri())
        imgs = browser.evaluate("Array.from(document.images).map(i => ({src: i.getAttribute('src').slice(0, 60), "
                                "complete: i.complete, w: i.naturalWidth, h: i.naturalHeight}))")
        title = browser.evaluate("document.title")
        n_scripts = browser.evaluate("document.scripts.length")
        width = browser.evaluate("document.documentElement.scrollWidth")
        if not embed:
            browser.screenshot(tmp_path / "report.png")
        errors = browser.errors()
        urls = browser.requested_urls()
    assert len(imgs) == 7
    bad = [i for i in imgs if not (i["complete"] and i["w"] > 0 and i["h"] > 0)]
    assert not bad, bad
    assert errors == []
    assert n_scripts == 0 and title.startswith("Report of <script>")  # escaped text, not an element
    assert all(u.startswith(("file:", "data:", "about:")) for u in urls), urls
    assert width <= 1300  # figures scale to the page, no horizontal overflow at 1280 px


def test_report_names_the_cluster_and_prints_dates_and_frequencies_readably(run_dir, tmp_path):
    """The run's cluster (run.json) in the header; an epoch as its full Julian date and UTC date, a frequency
    in MHz (a 4-digit float hid both: 2.458e+06, 4e+07); the products stage's own row in the timings."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    meta = json.loads((run / "run.json").read_text())
    meta["cluster"] = {"kind": "slurm", "jobs": 2, "job": {"cores": 1, "memory": "4GB", "walltime": "00:30:00"}}
    (run / "run.json").write_text(json.dumps(meta))
    top = json.loads((run / "maps" / "summary.json").read_text())
    top["maps"][0].update(epoch_jd=2458000.5, map_rms=12345.6)
    top["maps"][1]["freq_hz"] = 60.0244e6
    top["stages"] = {"mmodes": {"wall_s": 12.5, "tasks": 4, "tasks_run": 4},
                     "products": {"wall_s": 2.0, "tasks": 2, "tasks_run": 2, "until": "the report"}}
    top["flux_scale"] = {"rows": [{"name": "Cyg A", "freq_hz": 40e6, "measured_jy": 2.1e4, "model_jy": 2.0e4,
                                   "ratio": 1.05, "reference": "test"}]}
    (run / "maps" / "summary.json").write_text(json.dumps(top))
    s = summary_from_run(run)
    assert s.cluster["kind"] == "slurm"
    assert [r["stage"] for r in s.stage_times] == ["mmodes", "products (until the report)"]
    write_report(run / "report.html", s)
    page = (run / "report.html").read_text()
    assert '<span id="cluster">on a SLURM cluster: 2 jobs (cores 1, memory 4GB, walltime 00:30:00)</span>' in page
    assert "2458000.50000 (2017-09-04 00:00:00 UTC)" in page and "2.458e+06" not in page
    assert "<td class=\"l\">40.000 MHz</td>" in page and "<td class=\"l\">60.0244 MHz</td>" in page
    assert "<td>40.000 MHz</td>" in page and "4e+07" not in page  # the flux-scale table's column too
    assert "12345.6" in page and "products (until the report)" in page
    assert check_report(run / "report.html") == []


@pytest.mark.parametrize("cluster, text", [
    ({"kind": "local", "workers": 2, "threads_per_worker": 1, "memory_limit": "auto"},
     "on a local cluster: 2 workers of 1 thread, memory limit auto each"),
    ({"kind": "synchronous"}, "in one process (dask's synchronous scheduler)"),
    ({"kind": "address"}, "on a dask cluster joined by its address"), ({}, "")])
def test_cluster_in_words(cluster, text):
    from mmflow.io.report import cluster_text

    assert cluster_text(cluster) == text
