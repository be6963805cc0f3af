"""The field kernel against its naive NumPy twin, and invariants the sphere tracer relies on."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_synth import field as naive_field

from minegeo.synth import build_world


@pytest.fixture(scope="module")
def world():
    return build_world("small", 3)


def _points_near_drifts(world, n, seed):
    rng = np.random.default_rng(seed)
    segs = world._arrays["void_prims"][world._arrays["void_type"] == 0]
    k = rng.integers(0, len(segs), n)
    u = rng.uniform(0, 1, n)[:, None]
    base = segs[k, 0:3] * (1 - u) + segs[k, 3:6] * u
    return base + np.column_stack([rng.uniform(-3.5, 3.5, (n, 2)), rng.uniform(-1.0, 5.5, n)])


def test_kernel_matches_naive_twin(world):
    P = _points_near_drifts(world, 3000, seed=1)
    # add points around the vehicle, the sump/railings and the rough zones
    rng = np.random.default_rng(2)
    for c in (world.T_world_vehicle[:3, 3] + [0, 0, 1.0], np.array(world.features["sump"]["centre"]),
              world._arrays["zones"][0, :3]):
        P = np.vstack([P, c + rng.normal(0, 1.5, (500, 3))])
    a = world._arrays
    for with_noise, with_structures in ((True, True), (False, False), (True, False)):
        got = world.sdf(P, with_noise=with_noise, with_structures=with_structures)
        want = naive_field(P, a, world.T_world_vehicle, with_noise, with_structures)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_field_sign_and_structures_only_remove_space(world):
    P = _points_near_drifts(world, 2000, seed=3)
    full = world.sdf(P)
    bare = world.sdf(P, with_structures=False)
    assert np.all(full <= bare)
    assert (full > 0).mean() > 0.3 and (full < 0).mean() > 0.1


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), r=st.floats(0.001, 0.6))
def test_lipschitz_bound_used_by_sphere_tracing(world, seed, r):
    """|f(p) - f(q)| <= |p - q| / step_factor: a step of step_factor * f(p) never jumps the surface."""
    rng = np.random.default_rng(seed)
    P = _points_near_drifts(world, 200, seed)
    d = rng.normal(size=P.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Q = P + r * d
    L = 1.0 / world._arrays["step_factor"]
    assert np.all(np.abs(world.sdf(P) - world.sdf(Q)) <= L * r + 1e-12)
