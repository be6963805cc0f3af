"""Rough rock in the drift-network world (issue 18): one surface for the prior map and the frames."""

from __future__ import annotations

import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from minegeo.errors import InputError
from minegeo.synth.flight import FlightParams, NetworkWorld, _key, make_flight
from minegeo.synth.network import DriftNetwork, network_cloud, roughness_field, with_roughness


def _line():
    return DriftNetwork(np.array([[-30.0, 0.0], [30.0, 0.0]]), np.array([[0, 1]]), np.array([4.5]),
                        np.array([3.6, 3.6]))


def _rays(n=20000, seed=0):
    rng = np.random.default_rng(seed)
    D = rng.normal(size=(n, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    return np.tile([0.0, 0.3, 1.5], (n, 1)), D


def test_field_rms_seeded_and_checked():
    P = np.random.default_rng(1).uniform(-50, 50, (20000, 3))
    f = roughness_field(0.1, 3)
    assert np.sqrt(np.mean(f(P) ** 2)) == pytest.approx(0.1, rel=0.15)
    assert np.array_equal(f(P), roughness_field(0.1, 3)(P))
    assert not np.allclose(f(P), roughness_field(0.1, 4)(P))
    assert np.array_equal(roughness_field(0.0, 3)(P), np.zeros(len(P)))
    for bad in (-0.1, np.nan, np.inf):
        with pytest.raises(InputError):
            roughness_field(bad)


def test_frames_and_map_see_the_same_rock():
    """Ray hits of the rough world lie on the rough map (not on the flat one), on walls, floor and roof."""
    rough = with_roughness(_line(), 0.1, 3)
    O, D = _rays()
    t = NetworkWorld(rough).cast(O, D, 100.0)
    P = (O + t[:, None] * D)[np.isfinite(t)]
    P = P[np.abs(P[:, 0]) < 25]  # away from the rounded ends
    assert len(P) > 10000
    dense_rough = network_cloud(rough, 0.03, 0.0).points
    dense_flat = network_cloud(_line(), 0.03, 0.0).points
    d_rough = KDTree(dense_rough).query(P, k=1)[0]
    d_flat = KDTree(dense_flat).query(P, k=1)[0]
    # 3 cm sampling: a point on the surface is within ~2 cm of a sample
    assert np.median(d_rough) < 0.015 and np.quantile(d_rough, 0.95) < 0.03
    assert np.median(d_flat) > 0.04
    for lab in (0, 1, 2):  # each kind of surface is rough in the map
        L = network_cloud(rough, 0.2, 0.0)
        Q = L.points[L.labels == lab]
        F = network_cloud(_line(), 0.2, 0.0).points[L.labels == lab]
        assert np.sqrt(np.mean(np.sum((Q - F) ** 2, axis=1))) > 0.05


def test_zero_roughness_is_the_flat_world():
    net, flat = with_roughness(_line(), 0.0), _line()
    O, D = _rays(3000)
    assert np.array_equal(NetworkWorld(net).cast(O, D, 100.0), NetworkWorld(flat).cast(O, D, 100.0), equal_nan=True)
    assert np.array_equal(network_cloud(net, 0.2, 0.02, 7).points, network_cloud(flat, 0.2, 0.02, 7).points)
    fl = make_flight(flat, FlightParams(length_m=50.0, seed=0))
    # the frame cache: a flat network keeps its earlier key, a rough one has its own
    assert _key(net, fl) == _key(flat, fl) != _key(with_roughness(flat, 0.1, 3), fl)
    assert _key(with_roughness(flat, 0.1, 3), fl) != _key(with_roughness(flat, 0.1, 4), fl)
