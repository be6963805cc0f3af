"""Real data: pieces of the DARPA SubT Urban (Satsop) below-grade survey scan, moved by random
rigid transforms, are localized back in the whole scan (<= 0.1 m, <= 0.5 deg)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import shared_data

from minegeo.geometry.se3 import random_transform
from minegeo.localize import LocalizeParams, PrepareParams, localize_scan, prepare_map
from minegeo.localize.pipeline import error_vs_truth


@pytest.fixture(scope="module")
def satsop():
    from minegeo.io import read_point_cloud

    cloud = read_point_cloud(shared_data("subt_urban_satsop_scan", "Urban_Circuit_LowRes_Scan_alpha_LowerFloor.pcd.zip"))
    return cloud, prepare_map(cloud, PrepareParams.fast())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_satsop_crop_localized_back(satsop, seed):
    cloud, pm = satsop
    P = cloud.points
    rng = np.random.default_rng(seed)
    centre = P[rng.integers(P.shape[0])]
    piece = P[np.all(np.abs(P[:, :2] - centre[:2]) < 10.0, axis=1)]  # ~20 m x 20 m
    # a different sampling and noise than the map: keep 60 %, add 1 cm noise
    piece = piece[rng.random(piece.shape[0]) < 0.6]
    piece = piece + rng.normal(0.0, 0.01, piece.shape)
    T = random_transform(rng, np.pi, 100.0)  # any rotation, up to 100 m away
    scan = piece @ T[:3, :3].T + T[:3, 3]
    T_true = np.linalg.inv(T)
    T_true[:3, 3] += cloud.origin  # map frame = points + origin
    r = localize_scan(pm, scan, None, LocalizeParams.fast(), seed=seed)
    e = error_vs_truth(r.T_map_scan, T_true, scan)
    assert r.status == "ok", r.reason
    assert e["max_point_error_m"] <= 0.1, e
    assert e["rotation_deg"] <= 0.5, e
    assert r.position_95_radius_m < 0.1
