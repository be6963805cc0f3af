"""Monte Carlo check that the reported 95 % ellipse and azimuth interval are honest.

300 noisy scans of one scene; the fraction of trials whose true position lies inside the
reported 95 % ellipse (and true azimuth inside the 95 % interval) must fall inside the
binomial 99.9 % band around 95 % (for n = 300: about 90.7-98.3 %). The full 1000-trial
table over many configurations is in ``benchmarks/bench_mast.py`` / ``docs/mast.md``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from minegeo.mast import MastScenarioOptions, build_mast_world, locate_scanner

N_TRIALS = 300


def inside_reported_ellipse(res, x, y) -> bool:
    """Is the true (x, y) inside the reported ``ellipse95`` (semi-axes a, b; major-axis azimuth)?"""
    e = res.ellipse95
    t = math.radians(e["orientation_deg"])
    dx, dy = x - res.x_m, y - res.y_m
    u = dx * math.sin(t) + dy * math.cos(t)  # along the major axis
    v = dx * math.cos(t) - dy * math.sin(t)  # along the minor axis
    return (u / e["a_m"]) ** 2 + (v / e["b_m"]) ** 2 <= 1.0


@pytest.mark.slow
@pytest.mark.parametrize(
    "opts",
    [
        MastScenarioOptions(position=2, beacon1_rotation_deg=10.0, angular_step_deg=0.5, beacon_length_m=1.0),
        MastScenarioOptions(position=6, beacon1_rotation_deg=-10.0, angular_step_deg=0.5, beacon_length_m=1.0,
                            sigma_bearing_deg=0.01),
    ],
    ids=["divergent-pos2", "convergent-pos6-bearing-noise"],
)
def test_monte_carlo_coverage_of_95_percent_regions(opts):
    world = build_mast_world(opts, np.random.default_rng(1))
    x, y, az = opts.truth_pose()
    in_ell = in_az = solved = 0
    for k in range(N_TRIALS):
        scan, _ = world.noisy_scan(np.random.default_rng([99, k]))
        res = locate_scanner(scan, world.beacons)
        if not res.ok:
            continue
        solved += 1
        in_ell += inside_reported_ellipse(res, x, y)
        in_az += bool(abs(math.remainder(res.azimuth_deg - az, 360.0)) <= res.azimuth_ci95_deg)
    assert solved >= 0.99 * N_TRIALS
    lo, hi = (v / solved for v in stats.binom.interval(0.999, solved, 0.95))
    assert lo <= in_ell / solved <= hi, (in_ell / solved, lo, hi)
    assert lo <= in_az / solved <= hi, (in_az / solved, lo, hi)


@pytest.mark.slow
def test_beacon_survey_error_is_propagated_when_stated():
    """Beacons surveyed with 2 mm error: honest only if ``sigma_beacon_m`` says so."""
    from minegeo.mast import Beacon, MastParams

    opts = MastScenarioOptions(position=2, beacon1_rotation_deg=10.0, angular_step_deg=0.5)
    world = build_mast_world(opts, np.random.default_rng(1))
    x, y, _ = opts.truth_pose()
    n = 200
    hits = {0.0: 0, 0.002: 0}
    solved = {0.0: 0, 0.002: 0}
    for k in range(n):
        rng = np.random.default_rng([5, k])
        scan, _ = world.noisy_scan(rng)
        surveyed = [Beacon(b.beacon_id, b.vertices_m + rng.normal(size=(4, 2)) * 0.002) for b in world.beacons]
        for sv in hits:
            res = locate_scanner(scan, surveyed, MastParams(sigma_beacon_m=sv))
            if res.ok:
                solved[sv] += 1
                hits[sv] += inside_reported_ellipse(res, x, y)
    lo, hi = (v / solved[0.002] for v in stats.binom.interval(0.999, solved[0.002], 0.95))
    assert lo <= hits[0.002] / solved[0.002] <= hi
    assert hits[0.0] / solved[0.0] < 0.85  # ignoring the survey error overstates the precision
