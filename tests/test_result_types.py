"""Result types: every public result class is a frozen dataclass, and every status is a ``StrEnum`` member.

* **Frozen**: assigning a field of a result raises :class:`dataclasses.FrozenInstanceError` (checked on
  real results of cheap calls, and on every class of :data:`FROZEN_RESULTS` without building one).
  The classes left mutable are named in :data:`MUTABLE_BY_DESIGN` with the reason; a public
  ``*Result`` / ``*Outcome`` / ``*Estimate`` / ``*Evaluation`` dataclass must be in one of the two lists.
* **Statuses**: the ``status`` field of a result is annotated with a ``StrEnum`` and holds one of its
  members; a member is its string value for ``==``, ``json.dumps`` and f-strings (the bytes of
  ``result.json`` and of every CLI line are those of the plain strings).
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import pkgutil
import sys
from enum import StrEnum

import numpy as np
import pytest

import minegeo
from minegeo.features.fpfh import FPFHResult
from minegeo.geometry.normals import NormalsResult
from minegeo.geometry.octree import OctreeDownsampleResult
from minegeo.geometry.voxel import VoxelResult
from minegeo.georef.result import GeorefResult, GeorefStatus
from minegeo.localize.batch import BatchResult
from minegeo.localize.correlative import CorrelativeResult
from minegeo.localize.decision import Decision, DecisionStatus
from minegeo.localize.gravity_result import UpEstimate, UpStatus
from minegeo.localize.result import LocalizationResult, LocalizeStatus
from minegeo.localize.rival_check import RivalCheck
from minegeo.localize.rivals import RivalSearch
from minegeo.localize.uncertainty import PoseUncertainty
from minegeo.mast.icp import IcpResult
from minegeo.mast.pipeline import MastResult, MastStatus
from minegeo.optim.lm import LMOutcome, LMStatus
from minegeo.registration.gicp import GICPResult
from minegeo.registration.icp import ICPResult, ICPStatus
from minegeo.registration.ransac_params import RansacResult, RansacStatus
from minegeo.semantic.factors import FactorGraphResult
from minegeo.semantic.knowledge import IntersectionKB, KBParams, KBStatus
from minegeo.semantic.recognition import Recognition, RecognitionStatus
from minegeo.semantic.tracking import TrackResult, TrackStatus
from minegeo.slam.control import ControlResult, ControlStatus
from minegeo.slam.evaluate import TrajectoryEvaluation
from minegeo.slam.inertial import InertialResult
from minegeo.slam.loops import LoopCandidate
from minegeo.slam.mapping import NoiseRemovalResult
from minegeo.slam.odometry_model import OdometryResult
from minegeo.slam.pipeline import SlamResult
from minegeo.slam.planes import PlaneResult, PlaneStatus
from minegeo.slam.posegraph import PoseGraphResult
from minegeo.survey.helmert import Affine2DResult, Helmert2DResult, Helmert3DResult
from minegeo.survey.lsq import LSQResult
from minegeo.survey.network import NetworkResult, ObservationResult, PointResult
from minegeo.survey.resection import StationResult, StationStatus

#: public result classes: frozen
FROZEN_RESULTS = (
    LMOutcome, PlaneResult, NoiseRemovalResult, TrajectoryEvaluation, PoseGraphResult, SlamResult, LoopCandidate,
    ICPResult, GICPResult, RansacResult, FactorGraphResult, IntersectionKB, LocalizationResult, Decision, RivalCheck,
    UpEstimate, RivalSearch, CorrelativeResult, PoseUncertainty, BatchResult, StationResult, GeorefResult,
    MastResult, IcpResult, VoxelResult, OctreeDownsampleResult, NormalsResult, FPFHResult, Helmert2DResult,
    Affine2DResult, Helmert3DResult, LSQResult, NetworkResult, PointResult, ObservationResult, TrackResult,
    ControlResult, InertialResult, OdometryResult,
)
#: public result classes left mutable, by name: why
MUTABLE_BY_DESIGN = {
    "Recognition": "the tracker revises the status of a recognition it holds (a status set as a string is "
                   "stored as its RecognitionStatus member)",
    "LoopOutcome": "the state of the registration loop, updated at every iteration (registration/loop.py)",
}
#: result classes with a ``status`` field and the StrEnum it holds
STATUS_ENUMS = {
    LMOutcome: LMStatus, PoseGraphResult: LMStatus, FactorGraphResult: LMStatus, PlaneResult: PlaneStatus,
    ICPResult: ICPStatus, GICPResult: ICPStatus, RansacResult: RansacStatus, LocalizationResult: LocalizeStatus,
    Decision: DecisionStatus, RivalCheck: DecisionStatus, UpEstimate: UpStatus, StationResult: StationStatus,
    GeorefResult: GeorefStatus, MastResult: MastStatus, IntersectionKB: KBStatus, Recognition: RecognitionStatus,
    TrackResult: TrackStatus, ControlResult: ControlStatus, InertialResult: LMStatus,
}
RESULT_SUFFIXES = ("Result", "Outcome", "Estimate", "Evaluation")


def _public_result_classes() -> dict[str, type]:
    """Every dataclass named ``*Result`` (or a suffix of :data:`RESULT_SUFFIXES`) in the ``__all__`` of
    a public module of ``minegeo`` (the CLI left out)."""
    out = {}
    for m in pkgutil.walk_packages(minegeo.__path__, "minegeo."):
        if any(part.startswith("_") for part in m.name.split(".")) or m.name.startswith("minegeo.cli"):
            continue
        mod = importlib.import_module(m.name)
        for name in getattr(mod, "__all__", ()):
            obj = getattr(mod, name, None)
            if isinstance(obj, type) and dataclasses.is_dataclass(obj) and name.endswith(RESULT_SUFFIXES):
                out[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return out


def _assert_frozen(obj) -> None:
    f = dataclasses.fields(obj)[0].name
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(obj, f, getattr(obj, f, None))


def _assert_status(res, enum: type[StrEnum]) -> None:
    assert type(res.status) is enum, (type(res).__name__, type(res.status))
    assert res.status == res.status.value and json.dumps(res.status) == json.dumps(res.status.value)
    assert f"{res.status}" == f"{res.status:s}" == str(res.status) == res.status.value


def test_every_public_result_class_is_frozen_or_named_mutable():
    found = _public_result_classes()
    assert len(found) >= 20  # the walk sees the packages
    frozen = {f"{c.__module__}.{c.__qualname__}" for c in FROZEN_RESULTS}
    unlisted = sorted(k for k, c in found.items() if k not in frozen and c.__name__ not in MUTABLE_BY_DESIGN)
    assert not unlisted, f"classify these result classes (frozen, or mutable with a reason): {unlisted}"


@pytest.mark.parametrize("cls", FROZEN_RESULTS, ids=lambda c: c.__name__)
def test_result_class_is_frozen(cls):
    assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
    _assert_frozen(object.__new__(cls))  # a frozen dataclass refuses the assignment before looking at the value


@pytest.mark.parametrize("cls", list(STATUS_ENUMS), ids=lambda c: c.__name__)
def test_status_field_is_annotated_with_its_strenum(cls):
    owner = next(c for c in cls.__mro__ if "status" in vars(c).get("__annotations__", {}))  # where it is declared
    ann = cls.__dataclass_fields__["status"].type
    hint = eval(ann, vars(sys.modules[owner.__module__])) if isinstance(ann, str) else ann  # noqa: S307
    assert hint is STATUS_ENUMS[cls] and issubclass(hint, StrEnum)


def test_strenum_members_print_and_serialise_as_their_values():
    s = LocalizeStatus.AMBIGUOUS
    assert json.dumps({"status": s, "k": [s]}) == '{"status": "ambiguous", "k": ["ambiguous"]}'
    assert f"{s}|{s:>10}|%s" % s == "ambiguous| ambiguous|ambiguous"
    assert s == "ambiguous" and s.upper() == "AMBIGUOUS" and type(str(s)) is str


# ---------------------------------------------------------------- real results of cheap calls


def _cloud(seed: int, n: int = 300) -> np.ndarray:
    """A corner of three perpendicular planes (every pose direction constrained), metres."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.0, 4.0, size=(n, 2))
    return np.concatenate([np.c_[u[:100], np.zeros(100)], np.c_[u[100:200, 0], np.zeros(100), u[100:200, 1]],
                           np.c_[np.zeros(n - 200), u[200:]]])


def test_icp_and_gicp_results_are_frozen_with_an_icp_status():
    from minegeo.registration import GICPParams, ICPParams, register_gicp, register_icp

    Q = _cloud(1)
    P = Q - [0.05, -0.03, 0.02]
    for res in (register_icp(P, Q, np.eye(4), ICPParams(max_correspondence_distance_m=0.5)),
                register_gicp(P, Q, np.eye(4), GICPParams(max_correspondence_distance_m=0.5))):
        _assert_status(res, ICPStatus)
        _assert_frozen(res)


def test_pose_graph_and_floor_plane_results():
    from minegeo.io.g2o import PoseGraph
    from minegeo.slam.planes import FloorPlaneParams, extract_floor_plane
    from minegeo.slam.posegraph import optimize_pose_graph

    T = np.eye(4)
    T[0, 3] = 1.0
    g = PoseGraph("SE3", np.arange(3), np.stack([np.eye(4)] * 3), np.array([[0, 1], [1, 2]]), np.stack([T, T]),
                  np.stack([np.eye(6)] * 2))
    res = optimize_pose_graph(g)
    _assert_status(res, LMStatus)
    _assert_frozen(res)
    rng = np.random.default_rng(2)
    floor = np.c_[rng.uniform(-5, 5, size=(400, 2)), np.zeros(400)]
    pl = extract_floor_plane(floor, [0.0, 0.0, 2.0], FloorPlaneParams(radius_m=15.0), seed=3)
    assert pl.status == "ok"
    _assert_status(pl, PlaneStatus)
    _assert_frozen(pl)
    few = extract_floor_plane(floor[:2], [0.0, 0.0, 2.0], FloorPlaneParams(radius_m=15.0), seed=3)
    _assert_status(few, PlaneStatus)
    assert few.status is PlaneStatus.TOO_FEW_POINTS


def test_station_and_georef_results():
    from minegeo.georef import GeorefParams, georeference
    from minegeo.io.types import ControlPoints
    from minegeo.survey import trilateration_2d

    ctrl = {"A": (0.0, 0.0), "B": (100.0, 0.0), "C": (0.0, 100.0)}
    d = {k: float(np.hypot(40.0 - x, 30.0 - y)) for k, (x, y) in ctrl.items()}
    st = trilateration_2d(ctrl, d, sigma_distance_m=0.01)
    _assert_status(st, StationStatus)
    _assert_frozen(st)
    local = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [10.0, 10.0, 1.0]])
    fit = georeference(ControlPoints(ids=["a", "b", "c", "d"], local_xyz=local, crs_enh=local + [219437.0, 612981.0, 214.0],
                                     sigma_enh_m=np.full((4, 3), 0.005), crs="EPSG:5186"), "EPSG:5186",
                       GeorefParams(model="rigid"))
    _assert_status(fit, GeorefStatus)
    _assert_frozen(fit)
    _assert_status(GeorefResult.from_dict(fit.as_dict()), GeorefStatus)


def test_knowledge_base_and_recognition_store_members_of_their_status():
    k = 0
    kb = IntersectionKB("no_intersections", "", np.arange(k), np.zeros(k, np.int64), np.zeros((k, 3)), np.zeros(k),
                        np.zeros(k + 1, np.int64), np.zeros((0, 3)), np.zeros((k, 1)), np.zeros((k, 1, 1)),
                        KBParams(), {})
    _assert_status(kb, KBStatus)  # a string given to the constructor is stored as its member
    _assert_frozen(kb)
    with pytest.raises(ValueError):
        IntersectionKB("fine", *[getattr(kb, f.name) for f in dataclasses.fields(kb)][1:])
    rec = Recognition("none")
    _assert_status(rec, RecognitionStatus)
    rec.status = "conflict"  # the tracker revises a recognition: the member is stored
    _assert_status(rec, RecognitionStatus)
    assert rec.status is RecognitionStatus.CONFLICT
