"""Every verb's ``report.html`` opened in a real browser: headless Chromium driven by Playwright.

The CLI verbs run on small inputs into a temporary folder laid out like ``minegeo demo``'s
(``mine/``, ``georef/``, ``mast/``, ``localize/scan_01/``, then ``report.html`` of the demo built
from their ``result.json``), plus a failing run of each verb that can fail (georef with GCPs in
km, mast with no beacon in view, localize of a random blob, adjust with a blunder). Each report
is opened from its ``file:`` URL and must:

* load nothing but itself and ``data:`` URIs (every request is recorded; anything else is
  aborted and fails the test; no ``<script>``, no external ``src``/``href``);
* log no console error and no page error, and decode every ``<img>`` (``naturalWidth > 0``;
  at least one figure per report: matplotlib is a core dependency);
* open with the status banner: ``#status`` with the expected ``data-status`` is the first
  visible element of the body, nothing visible lies above it, and the page's first text line
  starts with ``STATUS:``;
* link only to its own anchors (which exist) or, relatively, to files that exist.

One full-page screenshot per report goes to ``MINEGEO_REPORT_SHOTS`` (default: a temporary folder).

Needs Playwright (PyPI ``playwright``; never ``playwright install``) and Debian's Chromium
(``/usr/bin/chromium``, or ``MINEGEO_CHROMIUM``). Without them the tests are skipped with the
reason; with ``MINEGEO_REQUIRE_BROWSER=1`` (set by ``.ci/run``) they fail instead.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from _report_inputs import network_json

from minegeo.cli import main

REQUIRE = os.environ.get("MINEGEO_REQUIRE_BROWSER") == "1"
CHROMIUM = Path(os.environ.get("MINEGEO_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 # belt and braces: no host name resolves, so nothing could reach the network
                 "--host-resolver-rules=MAP * ~NOTFOUND"]
SEED = 1



def _missing() -> str | None:
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "Playwright is not installed (pip install playwright; the browser is Debian's chromium)"
    if not CHROMIUM.exists():
        return f"Chromium not found at {CHROMIUM} (apt-get install chromium, or set MINEGEO_CHROMIUM)"
    return None


def _no_browser(reason: str):
    if REQUIRE:
        pytest.fail(f"MINEGEO_REQUIRE_BROWSER=1 but {reason}", pytrace=False)
    pytest.skip(reason)


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """A Chromium context with a fresh profile (checked first: no CLI work without a browser)."""
    reason = _missing()
    if reason:
        _no_browser(reason)
    from playwright.sync_api import Error, sync_playwright

    profile = tmp_path_factory.mktemp("chromium-profile")
    with sync_playwright() as pw:
        try:
            ctx = pw.chromium.launch_persistent_context(str(profile), executable_path=str(CHROMIUM), headless=True,
                                                        args=CHROMIUM_ARGS, viewport={"width": 1280, "height": 900})
        except Error as exc:
            _no_browser(f"Chromium at {CHROMIUM} did not start: {str(exc).splitlines()[0]}")
        try:
            yield ctx
        finally:
            ctx.close()


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    d = os.environ.get("MINEGEO_REPORT_SHOTS")
    if d:
        Path(d).mkdir(parents=True, exist_ok=True)
        return Path(d)
    return tmp_path_factory.mktemp("screenshots")


# ------------------------------------------------------------------------------------ inputs


def _km_gcps(src: Path, dst: Path) -> Path:
    """The GCP file with its CRS coordinates in kilometres (a unit mistake: georef fails)."""
    out = []
    for ln in src.read_text(encoding="utf-8").splitlines():
        f = ln.split(",")
        if ln.startswith("#") or f[0] == "id" or len(f) < 7:
            out.append(ln)
            continue
        f[4:7] = [repr(float(v) / 1000.0) for v in f[4:7]]
        out.append(",".join(f))
    dst.write_text("\n".join(out) + "\n", encoding="utf-8")
    return dst


def _run(argv, ok=(0,)) -> None:
    code = main(["-q", *[str(a) for a in argv]])
    assert code in ok, f"minegeo {' '.join(map(str, argv))} exited {code}"


def _status(d: Path) -> str:
    return json.loads((d / "result.json").read_text(encoding="utf-8"))["status"]


@pytest.fixture(scope="module")
def reports(browser, tmp_path_factory):
    """Run every verb (ok and failing runs); ``{case: (report.html, expected data-status)}``."""
    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.mast.scenario import write_mast_scenario
    from minegeo.report.demo_report import plot_demo_png, write_demo_report

    root = tmp_path_factory.mktemp("reports")
    demo, bad = root / "demo", root / "failing"
    bad.mkdir()
    cases: dict[str, tuple[Path, str]] = {}

    # synth (its folder is the demo's mine)
    mine = demo / "mine"
    _run(["synth", mine, "--seed", SEED])
    cases["synth"] = (mine / "report.html", "OK")
    # adjust: clean network (PASSED) and one with a 5 cm blunder (chi-square FAILED, flagged in red)
    for name, blunder in (("adjust_passed", 0.0), ("adjust_failed", 0.05)):
        net = root / f"{name}.json"
        net.write_text(json.dumps(network_json(blunder)), encoding="utf-8")
        _run(["adjust", net, "--out", root / name])
        cases[name] = (root / name / "report.html", "PASSED" if blunder == 0 else "FAILED")
    # georef: ok, and GCPs in km (unit check fails)
    geo_map = demo / "map_geo.ply"
    _run(["georef", "--map", mine / "map.ply", "--gcps", mine / "gcps.csv", "--crs", "EPSG:5186",
          "--out", geo_map, "--report", demo / "georef"])
    cases["georef_ok"] = (demo / "georef" / "report.html", "OK")
    _run(["georef", "--map", mine / "map.ply", "--gcps", _km_gcps(mine / "gcps.csv", bad / "gcps_km.csv"),
          "--crs", "EPSG:5186", "--out", bad / "geo_km.ply", "--report", bad / "georef"], ok=(1,))
    cases["georef_failed"] = (bad / "georef" / "report.html", "FAILED")
    # prepare-map: its report sits beside the prepared map
    _run(["prepare-map", "--map", geo_map, "--out", root / "prepared" / "map.npz"])
    cases["prepare_map"] = (root / "prepared" / "map.npz.report.html", "OK")
    # mast: ok, and no beacon in view
    sc = write_mast_scenario(demo / "mast_scenario", seed=SEED)
    _run(["mast", "--scan", sc["scan"], "--beacons", sc["beacons"], "--out", demo / "mast"])
    cases["mast_ok"] = (demo / "mast" / "report.html", "OK")
    scf = write_mast_scenario(bad / "mast_scenario", seed=3, position=4, visible_beacons=())
    _run(["mast", "--scan", scf["scan"], "--beacons", scf["beacons"], "--out", bad / "mast"], ok=(1,))
    cases["mast_failed"] = (bad / "mast" / "report.html", "FAILED")
    # localize (another engineer's report; covered here): a scan of the mine, and a random blob
    loc = demo / "localize" / "scan_01"
    _run(["localize", "--map", geo_map, "--scan", mine / "scans" / "scan_01.ply", "--trajectory",
          mine / "trajectories" / "scan_01.txt", "--out", loc, "--seed", "0", "--profile", "fast"])
    cases["localize_ok"] = (loc / "report.html", "OK")
    blob = bad / "blob.ply"
    write_point_cloud(blob, PointCloud(points=np.random.default_rng(0).uniform([-10, -3, 0], [10, 3, 4], (20000, 3))))
    _run(["localize", "--map", geo_map, "--scan", blob, "--out", bad / "localize", "--seed", "0",
          "--profile", "fast"], ok=(1,))
    cases["localize_failed"] = (bad / "localize" / "report.html", "FAILED")
    # localize-batch (one local Dask worker): a scan of the mine and an empty file (its own FAILED folder)
    bscans = bad / "batch_scans"
    bscans.mkdir()
    shutil.copy2(mine / "scans" / "scan_01.ply", bscans / "scan_01.ply")
    (bscans / "empty.ply").write_bytes(b"")
    _run(["localize-batch", "--map", root / "prepared" / "map.npz", "--scans", bscans, "--out", root / "batch",
          "--workers", "1", "--seed", "0", "--profile", "fast"], ok=(1,))
    cases["localize_batch"] = (root / "batch" / "report.html", "WARNINGS")
    cases["localize_batch_failed_scan"] = (root / "batch" / "empty" / "report.html", "FAILED")
    assert json.loads((root / "batch" / "batch_result.json").read_text(encoding="utf-8"))["counts"] == \
        {"ok": 1, "ambiguous": 0, "failed": 1}
    # intersections build (a crossing and a T) and track (a drone flight through the crossing, with
    # --truth: the error map), and a track on a base without intersections (odometry only: FAILED)
    _intersection_reports(root, cases)
    # the inputs behave as intended (else the expected banners above would be wrong)
    assert _status(demo / "georef") == "ok" and _status(bad / "georef") == "failed"
    assert _status(demo / "mast") == "ok" and _status(bad / "mast") == "failed"
    assert _status(loc) == "ok" and _status(bad / "localize") == "failed"
    # demo summary from those results (the real demo takes ~20 s more; its CLI writes the same page)
    rows = [{"step": "synth", "time_s": 1.0, "status": "ok", "result": "small mine", "report": "mine/report.html"},
            {"step": "georef", "time_s": 1.0, "status": _status(demo / "georef"), "result": "<b>escaped</b>",
             "report": "georef/report.html"},
            {"step": "mast", "time_s": 1.0, "status": _status(demo / "mast"), "result": "x, y, azimuth",
             "report": "mast/report.html"},
            {"step": "localize scan_01", "time_s": 1.0, "status": _status(loc), "result": "placed",
             "report": "localize/scan_01/report.html"}]
    drive = np.column_stack([np.linspace(0.0, 40.0, 30), np.zeros(30), np.zeros(30)]) + [2.0e5, 5.5e5, 100.0]
    plan = plot_demo_png(drive, drive + 0.05, [("scan_01", drive[10] + 0.02, drive[10])], drive[0])
    write_demo_report(demo / "report.html", rows, SEED, 4.0, {"localize profile": "fast"}, plan_png=plan,
                      compile_s=0.0)
    cases["demo"] = (demo / "report.html", "OK")
    return cases


def _intersection_reports(root: Path, cases: dict) -> None:
    from minegeo.io import PointCloud, write_point_cloud, write_trajectory
    from minegeo.synth.flight import FlightParams, make_flight, simulate_flight
    from minegeo.synth.network import DriftNetwork, network_cloud

    net = DriftNetwork(np.array([(0, 0), (40, 0), (-20, 0), (0, 20), (0, -20), (40, 20), (40, -20)], float),
                       np.array([(2, 0), (0, 1), (0, 3), (0, 4), (1, 5), (1, 6)]), np.full(6, 4.5), np.full(7, 3.6))
    d = root / "intersections"
    d.mkdir()
    write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, seed=1).points))
    _run(["intersections", "build", "--map", d / "map.ply", "--out", d / "kb.npz"])
    cases["intersections"] = (d / "kb.npz.html", "OK")
    flight = make_flight(net, FlightParams(length_m=30.0, seed=SEED, azimuth_step_deg=1.0), route=[2, 0, 1])
    frames = simulate_flight(net, flight, d / "cache")
    f = d / "frames"
    f.mkdir()
    for k, (_, P) in enumerate(frames):
        write_point_cloud(f / f"{k:06d}.ply", PointCloud(points=P))
    (f / "times.txt").write_text("".join(f"{t:.6f}\n" for t in frames.truth.times_s), encoding="utf-8")
    write_trajectory(d / "truth.tum", frames.truth, "tum", coordinates="local")
    T = frames.truth.poses[0]
    start = [*(f"{v:.6f}" for v in T[:3, 3]), f"{np.degrees(np.arctan2(T[1, 0], T[0, 0])):.6f}"]
    _run(["track", "--frames", f, "--db", d / "kb.npz", "--out", d / "track", "--truth", d / "truth.tum",
          "--start", *start])
    cases["track"] = (d / "track" / "report.html", "OK")
    line = DriftNetwork(np.array([[-30.0, 0.0], [30.0, 0.0]]), np.array([[0, 1]]), np.array([4.5]), np.full(2, 3.6))
    write_point_cloud(d / "drift.ply", PointCloud(points=network_cloud(line, seed=2).points))
    _run(["intersections", "build", "--map", d / "drift.ply", "--out", d / "none.npz"], ok=(1,))
    _run(["track", "--frames", f, "--db", d / "none.npz", "--out", d / "track_none", "--start", *start], ok=(1,))
    cases["track_failed"] = (d / "track_none" / "report.html", "FAILED")
    assert _status(d / "track") == "ok" and _status(d / "track_none") == "no_intersections"


# ------------------------------------------------------------------------------------ the check

_INSPECT = """() => {
  const vis = (el) => {
    const s = getComputedStyle(el), r = el.getBoundingClientRect();
    return s.display !== 'none' && s.visibility !== 'hidden' && parseFloat(s.opacity) > 0 && r.width > 0
      && r.height > 0;
  };
  const st = document.getElementById('status');
  const first = Array.from(document.body.children).find(vis) || null;
  const others = Array.from(document.body.querySelectorAll('*'))
    .filter(e => e !== st && !(st && st.contains(e)) && vis(e));
  const refs = Array.from(document.querySelectorAll('[src],[href],[srcset],[poster],[data]'))
    .map(e => e.getAttribute('src') || e.getAttribute('href') || e.getAttribute('srcset')
              || e.getAttribute('poster') || e.getAttribute('data'));
  return {
    status: st ? {data: st.dataset.status, text: st.innerText, top: st.getBoundingClientRect().top,
                  visible: vis(st)} : null,
    firstIsStatus: first !== null && first === st,
    firstTag: first ? first.tagName + '#' + first.id : null,
    othersTop: others.length ? Math.min(...others.map(e => e.getBoundingClientRect().top)) : 1e9,
    firstLine: document.body.innerText.trim().split('\\n')[0],
    imgs: Array.from(document.images).map(i => ({src: (i.getAttribute('src') || '').slice(0, 40),
                                                 complete: i.complete, w: i.naturalWidth, h: i.naturalHeight})),
    scripts: document.querySelectorAll('script').length,
    stylesheets: document.querySelectorAll('link[rel~="stylesheet"], link[rel~="icon"], link[rel~="preload"]').length,
    refs: refs,
    links: Array.from(document.querySelectorAll('a[href]')).map(a => a.getAttribute('href')),
    ids: Array.from(document.querySelectorAll('[id]')).map(e => e.id),
  };
}"""


def check_report(ctx, path: Path, expected: str, shot: Path | None = None, min_images: int = 0) -> dict:
    """Open ``path`` in the browser context and assert the report contract (module docstring)."""
    url = path.resolve().as_uri()
    requests, failed, console, errors, aborted = [], [], [], [], []

    def route(r):
        u = r.request.url
        if u == url or u.startswith("data:"):
            r.continue_()
        else:
            aborted.append(u)
            r.abort()

    page = ctx.new_page()
    try:
        page.route("**/*", route)
        page.on("request", lambda r: requests.append(r.url))
        page.on("requestfailed", lambda r: failed.append(f"{r.url} ({r.failure})"))
        page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url, wait_until="load", timeout=60_000)
        info = page.evaluate(_INSPECT)
        if shot is not None:
            page.screenshot(path=str(shot), full_page=True)
    finally:
        page.close()
    name = path.parent.name
    # nothing loaded but the report itself and its data: URIs; nothing failed; no errors
    outside = [u for u in requests if u != url and not u.startswith("data:")]
    assert not outside and not aborted, f"{name}: requests outside the report: {outside or aborted}"
    assert not failed, f"{name}: failed requests: {failed}"
    assert not console and not errors, f"{name}: console errors {console}, page errors {errors}"
    assert info["scripts"] == 0 and info["stylesheets"] == 0, f"{name}: scripts or linked resources in the page"
    ext = [u for u in info["refs"] if u and (u.startswith("//") or (re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", u)
                                                                     and not u.startswith("data:")))]
    assert not ext, f"{name}: external references {ext}"
    # every figure decoded
    bad = [i for i in info["imgs"] if not (i["complete"] and i["w"] > 0 and i["h"] > 0)]
    assert not bad, f"{name}: images not decoded: {bad}"
    assert all(i["src"].startswith("data:image/png;base64,") for i in info["imgs"]), info["imgs"]
    assert len(info["imgs"]) >= min_images, f"{name}: {len(info['imgs'])} figure(s), expected >= {min_images}"
    # the status banner comes first
    st = info["status"]
    assert st is not None, f"{name}: no #status element"
    assert st["data"] == expected, f"{name}: data-status {st['data']!r}, expected {expected!r} ({st['text']})"
    assert st["visible"] and info["firstIsStatus"], f"{name}: first visible element is {info['firstTag']}"
    assert st["top"] <= info["othersTop"], f"{name}: something is drawn above the status banner"
    assert info["firstLine"].startswith(f"STATUS: {expected}"), f"{name}: first line {info['firstLine']!r}"
    # links: own anchors that exist, or relative links to files that exist
    for href in info["links"]:
        if href.startswith("#"):
            assert href[1:] in info["ids"], f"{name}: dangling anchor {href}"
        else:
            assert "://" not in href and not href.startswith("/"), f"{name}: non-relative link {href}"
            assert (path.parent / href).is_file(), f"{name}: link to a missing file {href}"
    return info


CASES = ["adjust_passed", "adjust_failed", "mast_ok", "mast_failed", "georef_ok", "georef_failed", "prepare_map",
         "localize_ok", "localize_failed", "localize_batch", "localize_batch_failed_scan", "synth", "demo",
         "intersections", "track", "track_failed"]


@pytest.mark.parametrize("case", CASES)
def test_report_in_browser(case, reports, browser, shots):
    path, expected = reports[case]
    assert path.is_file(), f"{case}: {path} was not written"
    info = check_report(browser, path, expected, shots / f"{case}.png",
                        min_images=1 if case != "localize_batch_failed_scan" else 0)
    if case == "demo":
        assert len([h for h in info["links"] if not h.startswith("#")]) == 4
    if case == "localize_ok":  # the status line says where the scan is, with its 95 % radius
        assert "position of the scan origin" in info["firstLine"] and "95 % radius" in info["firstLine"]


def test_check_catches_broken_reports(reports, browser, tmp_path):
    """The check itself fails on an external image, a broken data URI, a missing or late banner, a script."""
    src, _ = reports["mast_ok"]
    html = src.read_text(encoding="utf-8")
    body = html.index("<body>") + len("<body>")
    banner = re.search(r'<div id="status".*?</div>', html).group(0)
    broken = {
        "external image": html[:body] + '<img src="http://example.com/x.png">' + html[body:],
        "broken data URI": html.replace("data:image/png;base64,", "data:image/png;base64,AAAA", 1),
        "no banner": html.replace(banner, ""),
        "banner not first": html.replace(banner, "").replace("</h1>", "</h1>" + banner, 1),
        "wrong status": html.replace('data-status="OK"', 'data-status="FAILED"'),
        "script error": html[:body] + "<script>undefinedFunction()</script>" + html[body:],
        "external link": html[:body] + '<a href="https://example.com/">x</a>' + html[body:],
    }
    for what, text in broken.items():
        p = tmp_path / what.replace(" ", "_") / "report.html"
        p.parent.mkdir()
        p.write_text(text, encoding="utf-8")
        with pytest.raises(AssertionError):
            check_report(browser, p, "OK")
    shutil.copy(src, tmp_path / "report.html")
    check_report(browser, tmp_path / "report.html", "OK", min_images=1)  # the original passes
