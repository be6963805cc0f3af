"""Stage 2 of :func:`~minegeo.localize.localize_scan`: hypotheses of where the scan lies.

* :func:`ransac_hypotheses`: FPFH correspondences + RANSAC with edge-length pruning
  ([Baek2022 Eqs. 7-9], Table 3) in one or more runs; every distinct placement each run proposes
  (best, runner-up, further alternatives) becomes a :class:`~minegeo.localize.verification.Candidate`.
* :func:`correlative_hypotheses`: the whole-map correlative 4-DOF search of a levelled scan
  (:mod:`minegeo.localize.correlative`, a minegeo addition) adds the placements that FPFH + RANSAC
  cannot propose, after a plane-fitness pre-check without ICP.

Every placement maps the origin-subtracted scan ``D`` into the map's ``work`` frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from minegeo.io.types import Trajectory
from minegeo.localize.correlative import correlative_candidates
from minegeo.localize.params import LocalizeParams
from minegeo.localize.prepared import PreparedMap
from minegeo.localize.run_context import RunContext
from minegeo.localize.scan import ScanFeatures
from minegeo.localize.verification import Candidate, VerifyContext, distinct, verify
from minegeo.registration.ransac import register_ransac

__all__ = ["Hypotheses", "CorrelativeHypotheses", "ransac_hypotheses", "correlative_hypotheses"]


@dataclass(frozen=True)
class Hypotheses:
    """Outcome of :func:`ransac_hypotheses`: ``ransacs`` every RANSAC run (``ransacs[0]`` is
    ``LocalizationResult.ransac``) and ``candidates`` their distinct placements, best first."""

    ransacs: list
    candidates: list

    @property
    def r0(self):
        """The first RANSAC run."""
        return self.ransacs[0]


@dataclass(frozen=True)
class CorrelativeHypotheses:
    """Outcome of :func:`correlative_hypotheses`: ``candidates`` the input list plus the search's
    distinct placements that passed the pre-check, ``result`` the
    :class:`~minegeo.localize.correlative.CorrelativeResult`, ``precheck`` the plane fitness
    without ICP of each of its candidates."""

    candidates: list
    result: object
    precheck: list = field(default_factory=list)

    def record(self, p: LocalizeParams) -> dict:
        """``LocalizationResult.correlative``."""
        return {**self.result.to_dict(), "precheck_plane_fitness": list(self.precheck),
                "precheck_ratio": float(p.correlative.precheck_ratio)}


def ransac_hypotheses(pm: PreparedMap, sf: ScanFeatures, p: LocalizeParams, run: RunContext) -> Hypotheses:
    """``p.ransac_runs`` RANSAC runs of the scan's features against the map's, and their distinct
    hypotheses (``ambiguity.distance_m`` / ``ambiguity.angle_deg`` apart about the scan centroid).
    With ``seed = run.stage_seed("ransac")``, the first run draws from ``seed``, the others from seeds
    drawn by ``np.random.default_rng(seed)``. Records ``ransac`` seconds in ``run.timings``."""
    with run.timed("ransac", "RANSAC"):
        seed = run.stage_seed("ransac")
        rng = np.random.default_rng(seed)
        run_seeds = [seed] + [int(s) for s in rng.integers(0, 2**31 - 1, size=p.ransac_runs - 1)]
        f_index = pm.feature_index  # built once per map and process (timed in the first scan's RANSAC)
        ransacs = [register_ransac(sf.feature_points, pm.points, sf.fpfh, pm.features, p.ransac, seed=s,
                                   target_feature_index=f_index, check_target=False) for s in run_seeds]
    cand: list[Candidate] = []
    for i, rr in enumerate(ransacs):
        if rr.n_inliers > 0:
            cand.append(Candidate(f"ransac[{i}] best", rr.T_target_source, rr.fitness, rr.inlier_rmse_m))
            if len(rr.alternatives) > 1:
                for a, (Ta, fa, ea) in enumerate(rr.alternatives[1:]):
                    cand.append(Candidate(f"ransac[{i}] " + ("runner-up" if a == 0 else f"hypothesis {a + 2}"),
                                          Ta, fa, ea))
            elif rr.second_best_T_target_source is not None:
                cand.append(Candidate(f"ransac[{i}] runner-up", rr.second_best_T_target_source,
                                      rr.second_best_fitness, rr.second_best_rmse_m))
    # drop duplicates (same placement as an earlier candidate)
    uniq: list[Candidate] = []
    for c in cand:
        if all(distinct(c[1], u[1], sf.centre, p) for u in uniq):
            uniq.append(c)
    return Hypotheses(ransacs=ransacs, candidates=uniq)


def reference_point(trajectory, scan_origin: np.ndarray) -> np.ndarray | None:
    """Median sensor position of the trajectory relative to the scan origin (scan axes, m), or
    None without a trajectory: the searches sample the scan around it."""
    if trajectory is not None and isinstance(trajectory, Trajectory) and len(trajectory.poses):
        return np.median(np.asarray(trajectory.poses)[:, :3, 3] + np.asarray(trajectory.origin) - scan_origin, axis=0)
    return None


def correlative_hypotheses(ctx: VerifyContext, pm: PreparedMap, uniq: list[Candidate], trajectory,
                           run: RunContext) -> CorrelativeHypotheses:
    """The correlative 4-DOF search of the whole map (levelled scans; its draws from ``run.stage_seed("correlative")``):
    its candidates whose plane fitness before ICP (feature-level scan at the refined 4-DOF placement)
    reaches ``correlative.precheck_ratio`` of the best such score and that are distinct from the list
    so far are appended to ``uniq``. Records ``correlative`` seconds in ``run.timings``."""
    p, sf = ctx.p, ctx.scan
    run.announce("correlative search")
    t0 = time.perf_counter()
    cp = p.correlative.search
    occ = pm.occupancy(cp)
    ref_xy = None
    if trajectory is not None and isinstance(trajectory, Trajectory) and len(trajectory.poses):
        ref_xy = np.median(np.asarray(trajectory.poses)[:, :2, 3] + np.asarray(trajectory.origin)[:2]
                           - sf.scan_origin[:2], axis=0)
    corr = correlative_candidates(occ, sf.feature_points, sf.feature_normals, p.correlative.search, seed=run.stage_seed("correlative"),
                                  reference_xy=ref_xy,
                                  refine_target=(pm.target_index(), ctx.Qf, ctx.Nf),
                                  screen_target=pm.screen_target(cp.screen_voxel_size_m),
                                  screen_grid=(pm.screen_grid(cp.screen_voxel_size_m)
                                               if cp.screen_grid and cp.screen_voxel_size_m is not None else None))
    # pre-check without ICP: plane fitness of the feature-level scan at each refined placement
    pre = [verify(sf.feature_points, Tc, ctx.Qf, ctx.Nf, ctx.tree, ctx.gate, ctx.tol)[0] for Tc, _ in corr.candidates]
    bar = float(p.correlative.precheck_ratio) * max(pre, default=0.0)
    out = list(uniq)
    for k, (Tc, frac) in enumerate(corr.candidates):
        if pre[k] >= bar and all(distinct(Tc, u[1], sf.centre, p) for u in out):
            out.append(Candidate(f"correlative #{k + 1}", Tc, frac, math.nan))
    run.timings["correlative"] = time.perf_counter() - t0
    return CorrelativeHypotheses(candidates=out, result=corr, precheck=pre)
