"""Inputs shared by the report tests (imported as ``_report_inputs``, like ``tests/badinput/_contract``)."""

from __future__ import annotations

import math

import numpy as np


def network_json(blunder_m: float = 0.0, seed: int = 3) -> dict:
    """A small 2D network: 4 control points, 3 new points, 10 distances (3 mm) and 6 angles (5").

    Observations are simulated from the true coordinates with seeded noise; ``blunder_m`` is
    added to the distance B-P2. Approximate coordinates of the new points are off by ~6 cm.
    """
    ctrl = {"A": (1000.0, 1000.0), "B": (1400.0, 1050.0), "C": (1350.0, 1450.0), "D": (950.0, 1400.0)}
    new = {"P1": (1150.0, 1150.0), "P2": (1250.0, 1300.0), "P3": (1100.0, 1320.0)}
    xy = {**ctrl, **new}
    rng = np.random.default_rng(seed)

    def az(a, b):
        return math.degrees(math.atan2(xy[b][0] - xy[a][0], xy[b][1] - xy[a][1])) % 360.0

    obs = []
    for a, b in [("A", "P1"), ("B", "P1"), ("P1", "P2"), ("P1", "P3"), ("B", "P2"), ("C", "P2"), ("P2", "P3"),
                 ("D", "P3"), ("A", "P3"), ("C", "P3")]:
        s = math.dist(xy[a], xy[b]) + rng.normal(0, 0.003) + (blunder_m if (a, b) == ("B", "P2") else 0.0)
        obs.append({"type": "distance", "from": a, "to": b, "value_m": round(s, 4), "sigma_m": 0.003})
    for at, fr, to in [("P1", "A", "B"), ("P1", "B", "P2"), ("P2", "B", "C"), ("P2", "C", "P3"),
                       ("P3", "D", "A"), ("P3", "C", "D")]:
        v = (az(at, to) - az(at, fr)) % 360.0 + rng.normal(0, 5.0) / 3600.0
        obs.append({"type": "angle", "at": at, "from": fr, "to": to, "value_deg": v, "sigma_arcsec": 5.0})
    pts = {k: {"x": v[0] + (0.05 if k in new else 0.0), "y": v[1] - (0.04 if k in new else 0.0)}
           for k, v in xy.items()}
    return {"name": "browser-test network" + (" with a blunder" if blunder_m else ""), "points": pts,
            "datum": {"type": "fix", "coordinates": list(ctrl)}, "observations": obs}
