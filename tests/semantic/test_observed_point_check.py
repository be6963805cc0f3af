"""Issue 29: the observed point check of the verification (``minegeo.semantic.recognition``, step 9).

A recognition is ``verified`` only when the observed invariant point ``z`` (keyframe frame), placed by
the ICP pose ``T_ICP`` (knowledge-base frame), lies within the gate floor ``RecognitionParams.gate_m`` of
the matched intersection's point ``C^i``; else ``rejected``. The ICP is replaced by a stub returning a
hand-built pose and a perfect fit, so the expected status comes from the hand-placed ``C^i``:
``C^i = T_ICP z + d u`` (``u`` a unit vector), verified iff ``d <= gate_m``.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from minegeo.semantic import recognition as R
from minegeo.semantic.recognition import PredictionGate, Recognition, RecognitionParams


def _pose(yaw_deg: float, t) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = t
    return T


#: the ICP pose of the levelled frame L (knowledge-base frame) and the keyframe in L
T_WL = _pose(37.0, [-15.0, -64.0, 1.3])
T_LK = _pose(-5.0, [0.0, 0.0, 1.2])
Z = np.array([4.2, -4.0, -1.2])                       # observed invariant point, keyframe frame (m)


def _verify(monkeypatch, d_m: float, u, gate=None, T_pred=None) -> Recognition:
    T_wk = T_WL @ T_LK
    x_obs = T_wk[:3, :3] @ Z + T_wk[:3, 3]             # hand calculation of where the ICP puts z
    u = np.asarray(u, float) / np.linalg.norm(u)
    kb = SimpleNamespace(invariant_points=np.array([x_obs + d_m * u]))
    icp = SimpleNamespace(inlier_rmse_m=0.05, fitness=1.0)
    monkeypatch.setattr(R, "_verify", lambda L, c_L, yaw, kb_, i, params: (T_WL.copy(), icp))
    rec = Recognition(R.RecognitionStatus.CANDIDATE, intersection_id=0, z_keyframe=Z.copy(), candidates=(0,))
    R._verify_step(rec, np.zeros((0, 3)), np.zeros(3), T_LK, SimpleNamespace(yaw_rad=0.0), kb,
                   RecognitionParams(), T_pred, None, gate, (0,))
    return rec


@pytest.mark.parametrize("d_m", [0.0, 0.8, 2.9, 3.1, 3.94, 8.0])
@pytest.mark.parametrize("u", [(1.0, 0.0, 0.0), (0.3, -1.0, 0.2), (0.0, 0.0, 1.0)])
def test_observed_point_beyond_the_floor_is_rejected(monkeypatch, d_m, u):
    rec = _verify(monkeypatch, d_m, u)
    floor = RecognitionParams().gate_m                   # 3 m
    assert rec.observed_to_named_m == pytest.approx(d_m, abs=1e-9)
    if d_m <= floor:
        assert rec.status == "verified", rec.reason
    else:
        assert rec.status == "rejected"
        assert "detected junction point" in rec.reason


def test_the_prediction_gate_alone_lets_the_displaced_point_through(monkeypatch):
    """The case of the NIOSH flight (3.94 m displaced, ICP pose right): a wide prediction covariance puts
    the named point inside the Mahalanobis gate and the ICP pose on the prediction, so only the observed
    point check refuses it."""
    T_pred = T_WL @ T_LK
    gate = PredictionGate(T_pred, np.diag([1e-4] * 3 + [4.0] * 3), 3.0)   # 2 m (1 sigma) per axis
    u = (1.0, 1.0, 0.0)
    x = T_pred[:3, :3] @ Z + T_pred[:3, 3] + 3.94 * np.array(u) / math.sqrt(2.0)
    assert gate.inside(Z, x) and gate.inside(np.zeros(3), T_pred[:3, 3])
    rec = _verify(monkeypatch, 3.94, u, gate=gate, T_pred=T_pred)
    assert rec.status == "rejected"
    assert _verify(monkeypatch, 1.0, u, gate=gate, T_pred=T_pred).status == "verified"
