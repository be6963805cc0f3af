"""The one report form without a browser: status decisions, parameters used, no-matplotlib fallback.

(The browser checks of every verb's page are in ``test_reports_browser.py``.)
"""

from __future__ import annotations

import json
import sys

import pytest
from _report_inputs import network_json

from minegeo.report import _html


def _adjust(tmp_path, blunder_m=0.0, **opts):
    from minegeo.survey import adjust_network, read_network
    from minegeo.survey.lsq import LSQOptions

    p = tmp_path / f"net_{blunder_m}.json"
    p.write_text(json.dumps(network_json(blunder_m)), encoding="utf-8")
    return adjust_network(read_network(p), LSQOptions(**opts))


@pytest.fixture
def no_matplotlib(monkeypatch):
    """Every ``matplotlib`` / ``mpl_toolkits`` import raises ImportError (as without the extra)."""
    for name in [m for m in sys.modules if m.split(".")[0] in ("matplotlib", "mpl_toolkits")] + \
            ["matplotlib", "mpl_toolkits"]:
        monkeypatch.setitem(sys.modules, name, None)


def test_adjust_status_passed_warnings_failed(tmp_path):
    from minegeo.report.survey_report import network_status, report_html

    ok = _adjust(tmp_path)
    assert network_status(ok)[0] == "PASSED"
    bad = _adjust(tmp_path, 0.05)
    word, why = network_status(bad)
    assert word == "FAILED" and "χ² global test FAILED" in why and "B-P2" in why
    # the same blunder with a χ² test that cannot fail: flagged observations alone give WARNINGS
    lax = _adjust(tmp_path, 0.02, alpha_global=1e-12)
    word, why = network_status(lax)
    assert lax.lsq.chi2.passed and word == "WARNINGS" and "flagged" in why
    html = report_html(lax, parameters={"confidence": 0.95, "alpha_global": 1e-12, "timings_s": {"x": 1.0}})
    assert html.index('data-status="WARNINGS"') < html.index("<h1>")
    assert "Parameters used" in html and "1e-12" in html and "timings_s" not in html


def test_adjust_headings_state_the_confidence_used(tmp_path):
    from minegeo.report.survey_report import report_html, report_text
    from minegeo.survey import adjust_network, read_network
    from minegeo.survey.lsq import LSQOptions

    p = tmp_path / "n.json"
    p.write_text(json.dumps(network_json()), encoding="utf-8")
    res = adjust_network(read_network(p), LSQOptions(), confidence=0.99)
    html = report_html(res, plot=False)
    assert "Plan view (99 % error ellipses)" in html and "a 99% [mm]" in html and "99% ellipses scaled" in html
    assert "95%" not in html and "95 % error ellipse" not in html
    assert "a 99% [mm]" in report_text(res) and "99% ellipses scaled" in report_text(res)


def test_reports_without_matplotlib(tmp_path, no_matplotlib):
    """Without the ``report`` extra every report is still written and says how to get the plot."""
    from minegeo.mast.scenario import write_mast_scenario
    from minegeo.report.mast_report import mast_report_html, plot_mast
    from minegeo.report.survey_report import plot_network_png, report_html

    res = _adjust(tmp_path)
    assert plot_network_png(res) is None
    html = report_html(res)
    assert _html.esc(_html.NO_PLOT) in html and "minegeo[report]" in html and "<img" not in html
    from minegeo.mast import locate_scanner, read_beacons_csv, read_scan_csv

    sc = write_mast_scenario(tmp_path / "sc", seed=1)
    beacons = read_beacons_csv(sc["beacons"])
    r = locate_scanner(read_scan_csv(sc["scan"]), beacons)
    assert plot_mast(r, beacons) is None
    html = mast_report_html(r, beacons, png=None)
    assert 'data-status="OK"' in html and "minegeo[report]" in html and "<img" not in html


def test_demo_status_and_links(tmp_path):
    from minegeo.report.demo_report import demo_report_html, demo_status

    row = {"step": "s", "time_s": 1.0, "status": "ok", "result": "", "report": None}
    assert demo_status([row])[0] == "OK"
    assert demo_status([row, {**row, "status": "ambiguous"}])[0] == "WARNINGS"
    assert demo_status([row, {**row, "status": "warning"}, {**row, "status": "failed"}])[0] == "FAILED"
    assert demo_status([row, {**row, "status": None}])[0] == "FAILED"  # a step that could not run
    html = demo_report_html([{**row, "report": "mine/report.html"}], 1)
    assert 'href="mine/report.html"' in html
    for link in ("/abs/report.html", "https://example.com/report.html", "C:\\x\\report.html"):
        with pytest.raises(ValueError):
            demo_report_html([{**row, "report": link}], 1)


def test_banner_id_is_unique_even_with_a_status_section():
    html = _html.page("t", [("Status", "<p>x</p>")], status="ok")
    assert html.count('id="status"') == 1 and 'id="status-section"' in html
    assert _html.status_word("warning") == "WARNINGS" and _html.status_word("ok") == "OK"
