"""MAST: fix a 2D scanner's position and azimuth from two surveyed wall beacons.

What a surveyor learns: a single horizontal scan that sees two three-panel beacons (surveyed in
the mine grid) gives the scanner's grid position and the azimuth of its zero-bearing axis, with
a covariance, sigma0 and a 95 % ellipse (Simela et al., MAST). The scene is simulated (paper
position 3, 3 mm range noise, mine grid coordinates near E 219 500 / N 612 900 handled with a
recorded local origin), written as the two CSV files you would bring from the field
(``scan.csv``, ``beacons.csv``), read back and solved; the truth is printed beside the answer.
A scan that sees only one beacon gives ``status = failed`` with the reason, never a guess.
Usage: ``python examples/mast_beacon_fix.py [OUTDIR]``.
"""

import sys
import tempfile

from minegeo.mast import MastParams, locate_scanner, read_beacons_csv, read_scan_csv, write_mast_scenario

out = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="mast_")
files = write_mast_scenario(out, seed=3, position=3, mine_origin_m=(219500.0, 612900.0))
scan, beacons = read_scan_csv(files["scan"]), read_beacons_csv(files["beacons"])
res = locate_scanner(scan, beacons, MastParams())
truth = __import__("json").loads(files["truth"].read_text(encoding="utf-8"))

print(f"files: {files['scan']}, {files['beacons']}  ({len(scan.range_m)} returns, {len(beacons)} beacons)")
print(f"status {res.status}  beacons used {res.details['beacons_used']}  sigma0 {res.sigma0:.2f}")
print(f"x = {res.x_m:.4f} m   (truth {truth['x_m']:.4f})")
print(f"y = {res.y_m:.4f} m   (truth {truth['y_m']:.4f})")
print(f"azimuth = {res.azimuth_dms} +/- {res.azimuth_ci95_deg * 3600:.0f}\" (95%)  (truth {truth['azimuth_deg']:.4f} deg)")
e = res.ellipse95
print(f"95% ellipse: a = {e['a_m'] * 1000:.1f} mm, b = {e['b_m'] * 1000:.1f} mm, major axis at {e['orientation_deg']:.1f} deg")

one = write_mast_scenario(f"{out}/one_beacon", seed=3, position=3, visible_beacons=("B2",))
bad = locate_scanner(read_scan_csv(one["scan"]), read_beacons_csv(one["beacons"]), MastParams())
print(f"only B2 visible -> status {bad.status}: {bad.reason}")
