"""Quick start: make the small synthetic mine and look at what is in it.

What a surveyor learns: what a complete minegeo data set looks like before touching real data —
a prior map (``map.ply``, mine "map" frame), local scans in their own sensor frames
(``scans/scan_XX.ply``), trajectories (TUM text), ground control points with their local and
projected (EPSG:5186) coordinates and standard deviations (``gcps.csv``), and ``truth.json``
holding the true transforms (``T_crs_map``, ``T_map_scan``) that every later step can be checked
against. The same seed always gives byte-identical files.
Usage: ``python examples/quickstart_synthetic_mine.py [OUTDIR]`` (OUTDIR must be empty).
"""

import sys
import tempfile
from pathlib import Path

from minegeo.io import read_gcps, read_point_cloud
from minegeo.synth import write_world

out = Path(sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="mine_"))
truth = write_world(out, "small", seed=1)

w = truth["world"]
print(f"mine: {w['n_drifts']} drifts, {w['total_length_m']:.0f} m of drift, {w['n_levels']} levels, "
      f"intersections {w['intersections_by_type']}")
cloud = read_point_cloud(out / "map.ply")
lo, hi = cloud.points.min(axis=0), cloud.points.max(axis=0)
print(f"map.ply: {len(cloud.points)} points, frame {cloud.frame!r}, extent "
      + " x ".join(f"{h - lo_:.0f}" for lo_, h in zip(lo, hi, strict=True)) + " m")
for s in truth["scans"]:
    print(f"  {s['file']}: {s['n_points']} points, {s['section']}, {s['sensor']['model']} on {s['carrier']}")
g = read_gcps(out / "gcps.csv")
print(f"gcps.csv: {len(g.ids)} control points in {g.crs}, sigma {g.sigma_enh_m[0, 0] * 1000:.0f} mm; first:")
print(f"  {g.ids[0]}: local {g.local_xyz[0].round(3).tolist()} -> E,N,H {g.crs_enh[0].round(3).tolist()}")
print(f"truth.json: T_crs_map translation {[round(v[3], 3) for v in truth['T_crs_map'][:3]]} m")
