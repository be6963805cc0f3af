"""minegeo.semantic: mine intersections as semantic landmarks (Liang et al. 2024).

The knowledge base of a prior map (:func:`build_knowledge_base`): drift skeleton and junctions
(:mod:`.skeleton`), geometric invariant points, dense intersection clouds, PWCV and CWC descriptors and
their heading-invariant similarity (:mod:`.descriptors`). See ``docs/intersections.md``.
"""

from __future__ import annotations

from minegeo.semantic.descriptors import (
    DescriptorParams,
    Similarity,
    completeness,
    cwc,
    pwcv,
    similarity,
    stack_keyframes,
)
from minegeo.semantic.knowledge import IntersectionKB, KBParams, build_knowledge_base, similarity_matrix
from minegeo.semantic.skeleton import Skeleton, SkeletonParams, drift_skeleton, invariant_point

__all__ = [
    "DescriptorParams",
    "Similarity",
    "completeness",
    "cwc",
    "pwcv",
    "similarity",
    "stack_keyframes",
    "IntersectionKB",
    "KBParams",
    "build_knowledge_base",
    "similarity_matrix",
    "Skeleton",
    "SkeletonParams",
    "drift_skeleton",
    "invariant_point",
]

# factor graph of Liang et al. 2024 Sec. 3 (minegeo/semantic/factors.py)
from minegeo.semantic.factors import (  # noqa: E402
    FactorGraph,
    FactorGraphResult,
    descriptor_completeness,
    intersection_covariance,
    relative_pose_covariance,
    relative_pose_information,
)

__all__ += [
    "FactorGraph",
    "FactorGraphResult",
    "descriptor_completeness",
    "intersection_covariance",
    "relative_pose_covariance",
    "relative_pose_information",
]

# online recognition and tracking (minegeo/semantic/recognition.py, tracking.py)
from minegeo.semantic.recognition import (  # noqa: E402
    Recognition,
    RecognitionParams,
    RecognitionState,
    recognise_keyframe,
)
from minegeo.semantic.tracking import TrackParams, TrackRecognition, TrackResult, TrackStatus, track  # noqa: E402

__all__ += ["Recognition", "RecognitionParams", "RecognitionState", "recognise_keyframe", "TrackParams",
            "TrackRecognition", "TrackResult", "TrackStatus", "track"]
