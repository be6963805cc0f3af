"""The synthetic mine geometry: determinism, profile, ramps, intersections, loop, roughness, vehicle."""

from __future__ import annotations

import math

import numpy as np
import pytest

from minegeo.errors import InputError
from minegeo.synth import MineWorld, build_world
from minegeo.synth.trajectory import _arc_lengths


@pytest.fixture(scope="module")
def world():
    return build_world("small", 1)


def _frame_at(world, drift, s_m):
    P = world.drifts[drift].centreline
    S = _arc_lengths(P)
    q = np.array([np.interp(s_m, S, P[:, i]) for i in range(3)])
    k = int(np.clip(np.searchsorted(S, s_m, side="right") - 1, 0, len(P) - 2))
    t = P[k + 1] - P[k]
    t[2] = 0
    t /= np.linalg.norm(t)
    return q, t, np.array([-t[1], t[0], 0.0])


def test_same_seed_identical_different_seed_differs(world):
    w2 = MineWorld.build("small", 1)
    for k, v in world._arrays.items():
        if isinstance(v, np.ndarray):
            assert np.array_equal(v, w2._arrays[k]), k
    assert np.array_equal(world.nodes, w2.nodes)
    w3 = build_world("small", 2)
    assert not np.array_equal(world._arrays["waves"], w3._arrays["waves"])
    assert not np.array_equal(world.nodes, w3.nodes)


def test_sign_convention(world):
    q, t, n = _frame_at(world, world.features["regular"]["drift"], world.features["regular"]["s_m"])
    inside = q + [0, 0, 2.0]
    rock = q + n * 8.0 + [0, 0, 2.0]
    f = world.sdf(np.array([inside, rock]), with_structures=False)
    assert f[0] > 1.5  # in the open drift, about half the width from the walls
    assert f[1] < 0
    assert world.sdf(inside[None])[0] > 0  # the parked vehicle is beside, not on, the centreline


def test_horseshoe_profile_4_5_m(world):
    """Design (noise-free) profile: 4.5 m between the walls, 4.5 m floor to crown, flat floor, arched roof."""
    d = world.features["regular"]["drift"]
    L = world.drifts[d].length_m
    O, D = [], []
    for s in np.linspace(0.3 * L, 0.7 * L, 5):
        q, t, n = _frame_at(world, d, s)
        c, side = q + [0, 0, 1.0], q + 1.5 * n + [0, 0, 1.0]
        up, down = [0, 0, 1.0], [0, 0, -1.0]
        O += [c, c, c, c, side, side]
        D += [n, -n, down, up, down, up]
    r = _smooth_cast(world, np.array(O), np.array(D)).reshape(5, 6)
    np.testing.assert_allclose(r[:, 0] + r[:, 1], 4.5, atol=5e-3)  # width
    np.testing.assert_allclose(r[:, 2], 1.0, atol=1e-3)  # floor under the centreline
    np.testing.assert_allclose(r[:, 4], 1.0, atol=1e-3)  # flat floor across the drift
    np.testing.assert_allclose(1.0 + r[:, 3], 4.5, atol=5e-3)  # crown height
    # arched roof: 1.5 m off-centre the roof is a half circle of radius 2.25 over 2.25 m walls
    np.testing.assert_allclose(1.0 + r[:, 5], 2.25 + math.sqrt(2.25**2 - 1.5**2), atol=5e-3)


def _smooth_cast(world, O, D):
    """Ranges against the smooth design profile (no roughness, no structures): grid search + bisection."""
    O = np.asarray(O, float)
    D = np.asarray(D, float)
    t = np.linspace(0, 8, 801)
    P = O[:, None, :] + t[None, :, None] * D[:, None, :]
    f = world.sdf(P.reshape(-1, 3), with_noise=False, with_structures=False).reshape(len(O), len(t))
    k = np.argmax(f <= 0, axis=1)
    lo, hi = t[k - 1], t[k]
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        free = world.sdf(O + mid[:, None] * D, with_noise=False, with_structures=False) > 0
        lo = np.where(free, mid, lo)
        hi = np.where(free, hi, mid)
    return 0.5 * (lo + hi)


def test_rough_walls_overbreak_up_to_about_0_3_m(world):
    """Walls with roughness: overbreak >= 0 up to ~0.3 m (more in the irregular zone), cm texture."""
    world = world.with_vehicle(None)
    d = world.features["regular"]["drift"]
    L = world.drifts[d].length_m
    over = []
    for s in np.linspace(0.2 * L, 0.8 * L, 40):
        q, t, n = _frame_at(world, d, s)
        for h in (0.8, 1.2, 1.6):
            o = q + [0, 0, h]
            r = world.cast(np.array([o, o]), np.array([-n, n]), 10.0, with_noise=True)
            over.extend(list(r - 2.25))
    over = np.array(over)
    over = over[np.isfinite(over)]
    assert over.min() > -0.1  # only structures (pipe/cables at the walls) come closer
    rock = over[over > -0.02]
    assert rock.max() < 0.62
    assert np.percentile(rock, 95) > 0.12  # genuinely rough, not a smooth tube
    assert rock.std() > 0.03


def test_ramp_slope_between_6_and_8_degrees(world):
    ramps = [d for d in world.drifts if d.kind == "ramp"]
    assert ramps
    for d in ramps:
        P = d.centreline
        dz = np.diff(P[:, 2])
        dxy = np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1)
        slope = np.degrees(np.arctan2(np.abs(dz), dxy))
        assert slope.min() >= 6.0 - 0.05 and slope.max() <= 8.0 + 0.05
        assert abs(P[0, 2] - P[-1, 2]) >= 10.0  # joins two levels
    # the built floor follows the slope: probe the floor height along the ramp
    d = ramps[0]
    S = _arc_lengths(d.centreline)
    ss = np.linspace(0.1 * S[-1], 0.3 * S[-1], 6)
    Q = np.array([_frame_at(world, world.drifts.index(d), s)[0] for s in ss])
    r = _smooth_cast(world, Q + [0, 0, 1.5], np.tile([0, 0, -1.0], (len(Q), 1)))
    z = Q[:, 2] + 1.5 - r
    fit = np.polyfit(ss, z, 1)
    ang = math.degrees(math.atan(abs(fit[0])))
    assert 6.0 - 0.1 <= ang <= 8.0 + 0.1


def test_intersections_loop_dead_ends(world):
    types = {it.type for it in world.intersections}
    assert {"T", "X", "Y"} <= types
    assert world.n_independent_loops() >= 2
    assert any(d.kind == "ring" for d in world.drifts)
    assert len(world.dead_ends) >= 2
    assert world.params.n_levels >= 2
    # an X junction is open in all four directions at 3 m from its centre
    X = next(it for it in world.intersections if it.type == "X")
    adj = world.adjacency()
    for k, _ in adj[X.node]:
        dft = world.drifts[k]
        P = dft.centreline if dft.a == X.node else dft.centreline[::-1]
        S = _arc_lengths(P)
        q = np.array([np.interp(3.0, S, P[:, i]) for i in range(3)])
        assert world.sdf((q + [0, 0, 1.5])[None], with_structures=False)[0] > 1.0


def test_curved_sections_exist(world):
    curved = 0
    for d in world.drifts:
        P = d.centreline
        v = np.diff(P[:, :2], axis=0)
        h = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
        if len(h) > 3 and np.ptp(h) > math.radians(60):
            curved += 1
    assert curved >= 2  # ring halves and the ramp turn


def test_vehicle_can_be_moved(world):
    park = world.features["parking"]
    centre = park[0][:3, :3] @ np.array([2.9, 0.0, 0.55]) + park[0][:3, 3]  # the loader's bucket
    assert world.sdf(centre[None])[0] < 0  # inside the parked vehicle
    moved = world.with_vehicle(park[1])
    assert moved.sdf(centre[None])[0] > 0.3
    assert world.with_vehicle(None).sdf(centre[None])[0] > 0.3
    assert world.sdf(centre[None])[0] < 0  # original unchanged (immutable)


def test_structures_present(world):
    a = world._arrays
    assert a["solid_prims"].shape[0] > 500  # bolts, straps, pipes, cables, duct, railings
    q, t, n = _frame_at(world, world.features["regular"]["drift"], world.features["regular"]["s_m"])
    # the ventilation duct hangs under the roof, right of the centreline
    duct_axis = q - 0.9 * n + [0, 0, 4.5 - 0.85]
    assert world.sdf(duct_axis[None])[0] < -0.3
    assert world.sdf(duct_axis[None], with_structures=False)[0] > 0.3


def test_bad_inputs():
    with pytest.raises(InputError):
        build_world("huge", 1)
    with pytest.raises(InputError):
        build_world("small", -1)


def test_summary_bounds(world):
    s = world.summary()
    assert s["total_length_m"] > 400
    lo, hi = world.bounds()
    assert np.all(hi - lo > 10)
    assert lo[2] < -10  # second level below
