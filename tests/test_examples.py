"""Every script in ``examples/`` runs to completion (exit 0) and prints its key result line.

Each runs in a subprocess with a temporary directory as its only argument (scripts that do not
write files ignore it), from a temporary working directory, so nothing lands in the checkout.
``render_synth_mine.py`` (figures, needs matplotlib and minutes of rendering) is not run here.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

#: script -> a fragment its output must contain
EXPECTED = {
    "quickstart_synthetic_mine.py": "gcps.csv: 10 control points in EPSG:5186",
    "adjust_resection.py": "U  E = 999.9989  N = 1000.0253",
    "mast_beacon_fix.py": "status ok  beacons used ['B1', 'B2']",
    "georeference_map.py": "GCP05 N + 6 cm: status warning",
    "register_scan_icp.py": "error vs truth:",
    "intersections_figures.py": "intersections: 5 found",
    "write_tiny_bag.py": "identical to what was written: True",
}
if (EXAMPLES / "localize_scan.py").exists():
    EXPECTED["localize_scan.py"] = "status ok"


def test_every_example_is_listed():
    scripts = {p.name for p in EXAMPLES.glob("*.py")} - {"render_synth_mine.py"}
    assert scripts == set(EXPECTED)


@pytest.mark.parametrize("script", sorted(EXPECTED))
def test_example_runs(script, tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, str(EXAMPLES / script), str(out)], cwd=tmp_path, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert EXPECTED[script] in r.stdout, r.stdout
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("script", ["adjust_resection.py", "georeference_map.py"])
def test_example_output_is_deterministic(script, tmp_path):
    runs = [subprocess.run([sys.executable, str(EXAMPLES / script), str(tmp_path / f"o{k}")], cwd=tmp_path,
                           capture_output=True, text=True, timeout=600).stdout for k in (1, 2)]
    assert runs[0] == runs[1] and runs[0]
