"""Settings and result of feature-based RANSAC registration (:class:`RansacParams`, :class:`RansacResult`) and the iteration count it needs.

Defaults follow Baek et al. 2022, Table 3; see :mod:`minegeo.registration.ransac` for the method.
Lengths in metres, angles in radians unless named ``_deg``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Literal

import numpy as np

from minegeo._params import bounded, flag, one_of, validate
from minegeo.errors import InputError

#: Sample modes (``RansacParams.mode``).
RansacMode = Literal["minegeo", "open3d"]
#: Edges compared by the edge-length check (``RansacParams.edge_pairs``).
EdgePairs = Literal["all", "polygon"]
#: Hypothesis models (``RansacParams.model``).
RansacModel = Literal["rigid", "levelled"]


@dataclass(frozen=True)
class RansacParams:
    """Parameters of :func:`register_ransac` (defaults: Baek et al. 2022, Table 3).

    Each field declares its bounds or choices in its metadata (:mod:`minegeo._params`): the same
    rule checks the dataclass and the command-line options that set the field (``minegeo localize
    --ransac-max-iterations``, ``--ransac-min-iterations``, ``--hypotheses``, ``--levelled``) and
    their keys in a ``--config`` file. ``ransac_n`` is at least 2, and at least 3 for the rigid
    model; the normal check needs the rigid model.

    Parameters
    ----------
    distance_threshold_m : float
        epsilon_distance (m): a source point transformed by a hypothesis is an
        inlier if its nearest target point is strictly closer than this; the
        same value is used for the distance check on the sample (Table 3: 2.5 m
        at a 0.5 m voxel; Open3D's tutorial uses 1.5 voxels).
    ransac_n : int
        Correspondences per sample, n in [Baek2022 Eq. 8] (Table 3: 4; Open3D default 3).
    edge_length_similarity : float
        Edge-length test of [Baek2022 Eq. 7]: an edge pair passes when
        ``min(d_p, d_q) >= s * max(d_p, d_q)``, i.e. ``eta <= 1 - s`` (Table 3: 0.9).
    edge_pairs : {"all", "polygon"}
        Edges compared: the closed polygon 1-2, 2-3, ..., n-1 ([Baek2022 Eq. 7]) or all
        pairs (Open3D). Identical for n = 3; "all" prunes more for n >= 4 and
        never rejects an exact sample, so it is the default.
    normal_angle_threshold_rad : float or None
        Optional normal check: reject a sample if ``n_q . (R n_p) < cos(angle)``
        for any pair (signed, as Open3D; needs consistently oriented normals).
    max_iterations : int
        Hard maximum of hypotheses drawn, N_max (Table 3: 4.0e8). With ``ransac_n=4`` and a
        low putative inlier ratio w, [Baek2022 Eq. 8] asks for ~log(1000)/w^4 draws (millions; about
        a microsecond each): use ``ransac_n=3`` or ``mutual_filter=True`` when speed matters.
    max_validations : int or None
        Stop after this many hypotheses passed the checks and were scored
        (Table 3: 500, Open3D <= 0.11's "max_validation"); None disables.
    confidence : float
        p of [Baek2022 Eq. 8] (not given in the paper; Open3D's default 0.999).
    mutual_filter : bool
        Keep only mutual descriptor nearest neighbours (Open3D rule, 10 % fallback).
    mode : {"minegeo", "open3d"}
        "minegeo": samples that repeat a correspondence or are collinear are
        rejected (they count as iterations), final least-squares refit on the
        inliers (``refit_iterations``).
        "open3d": samples drawn with replacement, no refit (the minimal-sample
        estimate is returned), as Open3D 0.20.
    refit_iterations : int
        Least-squares refits ([Baek2022 Eqs. 10-13] on all inliers) of the best and of the
        runner-up hypothesis; a refit is kept only if it scores better.
    batch_size : int
        Hypotheses drawn and scored per parallel batch. The result does not
        depend on the thread count; it does depend on ``batch_size`` through the
        order of random draws, so it is part of the recorded parameters.
    distinct_distance_m : float or None
        Two hypotheses are *distinct* if they place the source centroid more than
        this far apart (default ``2 * distance_threshold_m``) ...
    distinct_angle_deg : float
        ... or their rotations differ by more than this angle (deg).
    max_tilt_deg : float or None
        Levelled-frames prior (minegeo addition, not in the paper): when source and target
        frames both have z up (an IMU-levelled scan, a georeferenced map), reject every
        hypothesis whose rotation moves the vertical by more than this angle,
        ``arccos(e_z . R e_z) = arccos(R_33) > max_tilt_deg``. Such hypotheses count as
        iterations but are never scored. None (default) disables the check.
    min_iterations : int
        Floor of [Baek2022 Eq. 8]'s stopping rule (minegeo addition): the search never stops on [Baek2022 Eq. 8]
        before this many draws. [Baek2022 Eq. 8] takes ``w`` from the current best hypothesis; in a
        mine drift a *wrong* placement often explains a few percent of the putative pairs,
        which makes [Baek2022 Eq. 8] stop after ~10^4-10^5 draws, long before the right one (also at
        w of a few percent, ~10^6 draws for n = 3) is drawn. ``min_iterations =
        log(1 - p) / log(1 - w_min^n)`` encodes the smallest inlier ratio ``w_min`` the
        search must be able to find. 0 (default) = [Baek2022 Eq. 8] alone.
    model : {"rigid", "levelled"}
        "rigid" (default, the paper): 6-DOF hypotheses by SVD, ``ransac_n >= 3``.
        "levelled" (minegeo addition): both frames have z up (IMU-levelled scan,
        georeferenced map), so each hypothesis is a yaw + translation (4 DOF, closed-form
        2-D Procrustes, :func:`~minegeo.registration._kernels_ransac_levelled.yaw_fit`) and
        ``ransac_n = 2`` suffices: [Baek2022 Eq. 8] then needs ``~1/w²`` instead of ``~1/w³`` draws,
        which at the 0.3-2 % FPFH inlier ratios of a large mine map is the difference
        between 10⁴-10⁵ and 10⁵-10⁷ draws. Samples whose source points are less than
        ~1 m apart horizontally (spread < 0.5 m²) are degenerate. The normal check is not
        available with this model. Hypotheses are exactly level; ICP then refines all six
        degrees of freedom.
    n_hypotheses : int
        Distinct hypotheses returned in :attr:`RansacResult.alternatives` (best first;
        greedy by inlier count, then SSE, each distinct from all earlier ones). 2 (default)
        = best + runner-up; larger values switch off the runner-up bound pruning so every
        scored hypothesis keeps its full count.
    """

    distance_threshold_m: float = bounded(2.5, gt=0.0)
    ransac_n: int = bounded(4, ge=2, integer=True)
    edge_length_similarity: float = bounded(0.9, ge=0.0, le=1.0)
    edge_pairs: EdgePairs = one_of("all", EdgePairs)
    normal_angle_threshold_rad: float | None = bounded(None, ge=0.0, le=math.pi, optional=True)
    max_iterations: int = bounded(400_000_000, ge=1, integer=True)
    max_validations: int | None = bounded(500, ge=1, integer=True, optional=True)
    confidence: float = bounded(0.999, ge=0.0, le=1.0)
    mutual_filter: bool = flag(False)
    mode: RansacMode = one_of("minegeo", RansacMode)
    refit_iterations: int = bounded(3, ge=0, integer=True)
    batch_size: int = bounded(4096, ge=1, integer=True)
    distinct_distance_m: float | None = bounded(None, gt=0.0, optional=True)
    distinct_angle_deg: float = bounded(10.0, gt=0.0)
    max_tilt_deg: float | None = bounded(None, gt=0.0, le=180.0, optional=True)
    min_iterations: int = bounded(0, ge=0, integer=True)
    n_hypotheses: int = bounded(2, ge=2, integer=True)
    model: RansacModel = one_of("rigid", RansacModel)

    def __post_init__(self):
        validate(self)
        # checks across fields (each field's own rule is in its metadata)
        if self.model == "rigid" and self.ransac_n < 3:
            raise InputError(f"RansacParams.ransac_n must be a whole number >= 3 for the rigid model, got {self.ransac_n!r}")
        if self.model == "levelled" and self.normal_angle_threshold_rad is not None:
            raise InputError("RansacParams: the normal-angle check is not available with model='levelled'")

    @classmethod
    def open3d_compatible(
        cls,
        distance_threshold_m: float,
        ransac_n: int = 3,
        max_iterations: int = 100_000,
        confidence: float = 0.999,
        mutual_filter: bool = False,
        **kwargs,
    ) -> RansacParams:
        """Settings equivalent to Open3D's tutorial call (EdgeLength(0.9) + Distance(d) checkers)."""
        return cls(
            distance_threshold_m=distance_threshold_m,
            ransac_n=ransac_n,
            edge_length_similarity=kwargs.pop("edge_length_similarity", 0.9),
            edge_pairs="all",
            max_iterations=max_iterations,
            max_validations=None,
            confidence=confidence,
            mutual_filter=mutual_filter,
            mode="open3d",
            refit_iterations=0,
            **kwargs,
        )

    @property
    def distinct_distance(self) -> float:
        """Distinctness distance in metres (``distinct_distance_m`` or ``2 * distance_threshold_m``)."""
        return float(self.distinct_distance_m if self.distinct_distance_m is not None else 2 * self.distance_threshold_m)


class RansacStatus(StrEnum):
    """Status of a RANSAC registration (:attr:`RansacResult.status`); each member is its string value."""

    #: stopped by [Baek2022 Eq. 8]: the requested confidence was reached
    CONVERGED = "converged"
    #: stopped at ``max_iterations`` before [Baek2022 Eq. 8] held
    MAX_ITERATIONS = "max_iterations"
    #: stopped after ``max_validations`` scored hypotheses
    MAX_VALIDATIONS = "max_validations"
    #: no hypothesis passed the checks and explained any source point
    FAILED = "failed"


@dataclass(frozen=True)
class RansacResult:
    """Outcome of :func:`register_ransac`.

    Attributes
    ----------
    T_target_source : ndarray (4, 4)
        Best rigid transform, ``p_target = R p_source + t`` ([Baek2022 Eq. 9]). Identity if
        no hypothesis passed the checks (``status == "failed"``).
    fitness : float
        Inliers / source points (Open3D's fitness).
    inlier_rmse_m : float
        [Baek2022 Eq. 19] over the inlier pairs (m); 0 when there are none.
    n_inliers : int
        Source points with a target point strictly within ``distance_threshold_m``.
    iterations : int
        Hypotheses drawn (including those rejected by the checks).
    n_validations : int
        Hypotheses that passed the checks and were scored.
    converged : bool
        True if stopping came from [Baek2022 Eq. 8] (requested confidence reached).
    status : RansacStatus
        ``converged``, ``max_iterations``, ``max_validations`` or ``failed``.
    reason : str
        Human-readable explanation of ``status``.
    second_best_fitness, second_best_rmse_m : float
        Score of the runner-up: the best hypothesis *distinct* from the best
        (see :class:`RansacParams` ``distinct_*``), refitted like the best; NaN if
        none was scored.
    second_best_n_inliers : int
        Its inlier count (-1 if none).
    second_best_distance_m : float
        Distance between where the best and the runner-up place the source
        centroid (m); NaN if none.
    second_best_rotation_deg : float
        Rotation angle between the two hypotheses (deg); NaN if none.
    second_best_T_target_source : ndarray (4, 4) or None
        The runner-up transform.
    ambiguity_ratio : float
        ``second_best_n_inliers / n_inliers`` (0 if no runner-up); close to 1
        means another, distinct placement explains the data almost as well
        (e.g. a symmetric corridor) and the result should be flagged.
    correspondences : ndarray (k, 2)
        Putative (source, target) descriptor matches the samples were drawn from.
    inlier_pairs : ndarray (n_inliers, 2)
        (source, target) nearest-neighbour pairs of the final transform.
    mutual_applied : bool
        Whether the mutual filter was applied to ``correspondences``.
    params : RansacParams
    seed : int or None
    timings_s : dict
        Seconds per stage (``correspondences``, ``grid``, ``hypotheses``, ``refit``, ``total``).
    alternatives : tuple of (T (4, 4), fitness, inlier_rmse_m)
        Up to ``params.n_hypotheses`` mutually distinct hypotheses, best first (the first is
        the best hypothesis, refitted); each refitted like the best.
    n_tilt_rejected : int
        Hypotheses rejected by the ``max_tilt_deg`` check.
    """

    T_target_source: np.ndarray
    fitness: float
    inlier_rmse_m: float
    n_inliers: int
    iterations: int
    n_validations: int
    converged: bool
    status: RansacStatus
    reason: str
    second_best_fitness: float
    second_best_rmse_m: float
    second_best_n_inliers: int
    second_best_distance_m: float
    second_best_rotation_deg: float
    second_best_T_target_source: np.ndarray | None
    ambiguity_ratio: float
    correspondences: np.ndarray
    inlier_pairs: np.ndarray
    mutual_applied: bool
    params: RansacParams
    seed: int | None
    timings_s: dict = field(default_factory=dict)
    alternatives: tuple = ()
    n_tilt_rejected: int = 0

    @property
    def second_best_score(self) -> float:
        """Score of the runner-up in the units of ``fitness`` (same as ``second_best_fitness``)."""
        return self.second_best_fitness


# ----------------------------------------------------------------------------- helpers


def required_iterations(w: float, n: int, confidence: float) -> float:
    """[Baek2022 Eq. 8]: ``N = log(1 - p) / log(1 - w^n)`` (may be inf; NaN-free).

    Parameters
    ----------
    w : float
        Inlier fraction of the putative correspondences under the current best.
    n : int
        Sample size.
    confidence : float
        Desired success probability p.

    Returns
    -------
    float
        ``inf`` when ``w = 0`` or ``p = 1`` (never stop early), 0 when ``w = 1``.
    """
    wn = float(w) ** int(n)
    if wn <= 0.0 or confidence >= 1.0:
        return math.inf
    if wn >= 1.0:
        return 0.0
    if confidence <= 0.0:
        return 0.0
    return math.log(1.0 - confidence) / math.log(1.0 - wn)
