"""Study worlds: synthetic mines for localization where drifts look alike.

:func:`make_study_world` builds a world with the study options of
:class:`~minegeo.synth.world.WorldParams` (wall roughness, repeated levels, unmapped headings),
its survey map, and draws scans of three classes with their ground truth:

* ``"mapped"``: an ordinary place of a mapped drift (in a repeated-level world: a drift
  without a copy, i.e. the helical decline);
* ``"twin"``: the middle of a drift that has a copy on another level. In an ``"exact"`` world
  the raw scan is simulated again from every copy's pose and the copy is listed only when
  every point agrees within :data:`TWIN_TOL_M` (the scans are then indistinguishable); in a
  ``"near"`` world the label is ``"near_twin"`` and the copies' poses are listed unverified;
* ``"unmapped"``: deep inside a heading the map does not hold (its path stays at least
  :data:`HEADING_MIN_S_M` from the mouth, beyond the bend).

Every scan is re-expressed in a *levelled* frame (z up, uniformly random heading, optional
IMU tilt error) or an *unlevelled* one (uniformly random rotation of SO(3)), with its origin at
the sensor's first position; ``T_map_scan`` is the truth. Everything derives from the seeds:
the same arguments give bit-identical arrays.

The wall-roughness helpers (:func:`sample_wall_points`, :func:`measure_wall_roughness`)
measure the std of the bump field that ``WorldParams.wall_roughness_m`` sets.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from minegeo.errors import DegenerateGeometryError, InputError
from minegeo.io.types import PointCloud, Trajectory
from minegeo.synth.dataset import _frame_stride, _section_path, _to_scan_frame, build_survey_map
from minegeo.synth.sensors import ZebRevo, simulate_scan
from minegeo.synth.trajectory import make_trajectory
from minegeo.synth.world import PRESETS, MineWorld, build_world
from minegeo.synth.world_primitives import _assemble, _cast_arrays, _smooth_field

__all__ = ["StudyScan", "StudyWorld", "make_study_world", "sample_wall_points", "measure_wall_roughness",
           "TWIN_TOL_M", "HEADING_MIN_S_M", "SCAN_LABELS"]

log = logging.getLogger(__name__)

#: two raw scans are "the same" when every point agrees within this (m): the sphere tracer refines
#: hits to 1e-4 m, so floating-point noise between copies can move a hit by up to that much.
TWIN_TOL_M = 1e-3
#: scans of an unmapped heading keep their whole path at least this far (m, along the heading) from
#: its mouth: past the 12 m first leg and the 60-90 degree bend, so the mapped drift is out of sight.
HEADING_MIN_S_M = 30.0
#: scan classes drawn by :meth:`StudyWorld.draw_scans` (``"twin"`` is labelled ``"near_twin"`` in a near world)
SCAN_LABELS = ("mapped", "twin", "unmapped")


@dataclass
class StudyScan:
    """One drawn scan with its truth.

    Attributes
    ----------
    cloud : PointCloud
        Points in the scan frame (``frame="scan"``, m), with ``time_s`` and ``range_m``.
    trajectory : Trajectory
        ``T_scan_sensor`` over the walk.
    T_map_scan : (4, 4) ndarray
        Ground truth: scan frame -> map frame.
    label : str
        ``"mapped"``, ``"twin"`` (exact twin, verified), ``"near_twin"`` or ``"unmapped"``.
    drift, s_m : int, float
        Drift index and arc length (m) the scan path is centred on.
    length_m : float
        Scan length along the drift (m).
    levelled : bool
        Levelled frame (z up, random heading) or a uniformly random rotation.
    seed : int
        Seed of the carrier's sway (``seed + 1``: range noise).
    twins_T_map_scan : tuple of (4, 4) ndarray
        The same scan placed on the other levels (``"twin"``: every pose from which the raw scan
        was re-simulated identically; ``"near_twin"``: the copies' poses, unverified). A
        localizer that reports ``T_map_scan`` or any of these is equally right.
    twin_max_abs_diff_m : float or None
        Largest coordinate difference (m) between the raw scan and its re-simulation from a
        listed twin pose (``"twin"`` only).
    mapped_fraction : float
        Fraction of the points on mapped drifts (closer to a mapped drift's design surface than
        to an unmapped one's); 1 in worlds without unmapped drifts.
    """

    cloud: PointCloud
    trajectory: Trajectory
    T_map_scan: np.ndarray
    label: str
    drift: int
    s_m: float
    length_m: float
    levelled: bool
    seed: int
    twins_T_map_scan: tuple = ()
    twin_max_abs_diff_m: float | None = None
    mapped_fraction: float = 1.0


@dataclass
class StudyWorld:
    """A study world, its survey map and the options it was built with (see :func:`make_study_world`).

    Attributes
    ----------
    world : MineWorld
    map : PointCloud
        Survey map (``frame="map"``) of :func:`~minegeo.synth.dataset.build_survey_map` (unmapped
        drifts absent).
    options : dict
        The arguments of :func:`make_study_world`.
    """

    world: MineWorld
    map: PointCloud
    options: dict
    _unmapped_arrays: dict | None = field(default=None, repr=False)

    # ------------------------------------------------------------------ drawing
    def draw_scans(self, n: int, length_m: float, label: str = "mapped", *, levelled: bool = True, seed: int = 0,
                   sensor=None, kind: str = "walk", max_rays: int = 50_000, tilt_sigma_deg: float = 0.0,
                   max_tries: int = 40) -> list[StudyScan]:
        """Draw ``n`` scans of ``length_m`` of one class.

        Parameters
        ----------
        n : int
            Number of scans.
        length_m : float
            Scan length along the drift (m): 10, 20 or 30 in the study.
        label : {"mapped", "twin", "unmapped"}
            Class (see the module docstring). ``"twin"`` needs repeated levels, ``"unmapped"``
            unmapped headings.
        levelled : bool
            True: the scan frame is levelled (z up) with a uniformly random heading (and a tilt of
            ``|N(0, tilt_sigma_deg^2)|`` about a random horizontal axis); False: the scan frame is
            rotated by a uniformly random rotation (Shoemake's uniform quaternion).
        seed : int
            Seeds the places, carriers, noise and frames; the draw is a function of
            ``(world seed, seed, label, length_m, levelled)`` only.
        sensor : sensor model, optional
            Default :class:`~minegeo.synth.sensors.ZebRevo` (30 m range).
        kind : str
            Carrier (``walk``, ``drive``, ``fly``, ``handheld``).
        max_rays : int
            Beams cast per scan (frames thinned as in :func:`~minegeo.synth.dataset.local_scan`).
        tilt_sigma_deg : float
            IMU levelling error of levelled frames (degrees).
        max_tries : int
            Places tried per scan before giving up.

        Returns
        -------
        list of StudyScan

        Raises
        ------
        InputError
            Unknown label, a class this world does not have, or no acceptable place found.
        """
        if label not in SCAN_LABELS:
            raise InputError(f"label must be one of {SCAN_LABELS}, got {label!r}")
        if not (isinstance(n, (int, np.integer)) and n >= 0):
            raise InputError(f"n must be an integer >= 0, got {n!r}")
        if not length_m > 0:
            raise InputError(f"length_m must be > 0, got {length_m}")
        sensor = ZebRevo() if sensor is None else sensor
        rng = np.random.default_rng([int(self.world.seed), int(seed), SCAN_LABELS.index(label),
                                     int(round(float(length_m) * 1000)), int(bool(levelled))])
        return [self._draw_one(rng, float(length_m), label, bool(levelled), sensor, kind, int(max_rays),
                               float(tilt_sigma_deg), int(max_tries)) for _ in range(int(n))]

    def _candidates(self, label: str) -> tuple[list[int], np.ndarray]:
        w = self.world
        um = set(w.unmapped)
        if label == "unmapped":
            ks = sorted(um)
            if not ks:
                raise InputError("this study world has no unmapped drifts (unmapped=0)")
        elif label == "twin":
            if w.repeat is None:
                raise InputError("this study world has no repeated levels (twins='none')")
            ks = [k for k in range(len(w.drifts)) if k not in um and w.twins(k)]
        else:
            ks = [k for k in range(len(w.drifts)) if k not in um and not w.twins(k)]
        L = np.array([w.drifts[k].length_m for k in ks])
        if label == "unmapped":
            keep = L > HEADING_MIN_S_M + 1.0
            ks, L = [k for k, ok in zip(ks, keep, strict=True) if ok], L[keep]
        if not ks:
            raise InputError(f"no drift of class {label!r} in this study world")
        return ks, L

    def _place(self, rng, label: str, length_m: float) -> tuple[int, float]:
        ks, L = self._candidates(label)
        i = int(rng.choice(len(ks), p=L / L.sum()))
        k, Lk = ks[i], float(L[i])
        if label == "twin":
            s = rng.uniform(0.35, 0.65) * Lk
        elif label == "unmapped":
            lo = min(HEADING_MIN_S_M + length_m / 2.0, Lk - 0.5)
            s = rng.uniform(lo, Lk - 0.5)
        else:
            s = rng.uniform(0.0, Lk)
        return k, float(s)

    def _draw_one(self, rng, length_m, label, levelled, sensor, kind, max_rays, tilt_sigma_deg, max_tries):
        w = self.world
        exact = w.repeat is not None and w.repeat["mode"] == "exact"
        for _ in range(max_tries):
            k, s = self._place(rng, label, length_m)
            sseed = int(rng.integers(0, 2**31 - 1))
            frame_u = rng.uniform(size=8)  # drawn whether used or not: places do not shift the stream
            try:
                path, _ = _section_path(w, {"drift": k, "s_m": s}, length_m)
                traj = make_trajectory(w, kind, path=path, seed=sseed, rate_hz=50.0)
            except DegenerateGeometryError:
                continue
            fs = _frame_stride(traj, sensor, max_rays, None)
            raw = simulate_scan(w, sensor, traj, seed=sseed + 1, frame_stride=fs)
            if len(raw) < 100:
                continue
            cloud, traj_scan, T_map_scan = _to_scan_frame(raw, traj, traj.poses[0].copy())
            frac = self.mapped_fraction(cloud.points @ T_map_scan[:3, :3].T + T_map_scan[:3, 3])
            twins, diff, out_label = (), None, label
            if label == "mapped" and frac < 0.99:
                continue  # sees into an unmapped heading: not an ordinary mapped place
            if label == "unmapped" and frac > 0.01:
                continue
            if label == "twin":
                offs = [o for _, o in w.twins(k)]
                if exact:
                    offs, diff = self._verify_twins(raw, traj, sensor, sseed, fs, offs)
                    if not offs:
                        continue
                else:
                    out_label = "near_twin"
                twins = tuple(offs)
            T_out = _frame(T_map_scan, levelled, frame_u, tilt_sigma_deg)
            A = np.linalg.solve(T_out, T_map_scan)  # scan frame -> output frame
            pts = cloud.points @ A[:3, :3].T + A[:3, 3]
            out = PointCloud(points=np.ascontiguousarray(pts), attributes=dict(cloud.attributes), frame="scan")
            poses = np.einsum("ij,njk->nik", A, traj_scan.poses)
            tr = Trajectory(times_s=traj_scan.times_s, poses=poses, frame="scan", body="sensor")
            tw = []
            for o in twins:
                T = T_out.copy()
                T[:3, 3] += o
                tw.append(T)
            return StudyScan(cloud=out, trajectory=tr, T_map_scan=T_out, label=out_label, drift=k, s_m=s,
                             length_m=length_m, levelled=levelled, seed=sseed, twins_T_map_scan=tuple(tw),
                             twin_max_abs_diff_m=diff, mapped_fraction=frac)
        raise InputError(f"no acceptable place for a {length_m:g} m {label!r} scan after {max_tries} tries")

    def _verify_twins(self, raw, traj, sensor, sseed, fs, offsets):
        """Offsets from which the same raw scan is simulated (within TWIN_TOL_M), and the largest difference."""
        ok, worst = [], 0.0
        for o in offsets:
            poses = traj.poses.copy()
            poses[:, :3, 3] += o
            t2 = Trajectory(times_s=traj.times_s, poses=poses, frame=traj.frame, body=traj.body)
            raw2 = simulate_scan(self.world, sensor, t2, seed=sseed + 1, frame_stride=fs)
            if len(raw2) != len(raw) or not np.array_equal(raw2.attributes["time_s"], raw.attributes["time_s"]):
                continue
            d = float(np.abs(raw2.points - raw.points).max()) if len(raw) else 0.0
            if d <= TWIN_TOL_M:
                ok.append(np.asarray(o, float))
                worst = max(worst, d)
        return ok, (worst if ok else None)

    # ------------------------------------------------------------------ truth helpers
    def mapped_fraction(self, points_world) -> float:
        """Fraction of world points closer to a mapped drift's design surface than to an unmapped one's."""
        w = self.world
        P = np.ascontiguousarray(np.asarray(points_world, float).reshape(-1, 3))
        if not w.unmapped or len(P) == 0:
            return 1.0
        if self._unmapped_arrays is None:
            a = w._arrays
            keep = np.isin(w._extra["void_owner"], np.array(sorted(w.unmapped), np.int64))
            self._unmapped_arrays = _assemble(a["void_prims"][keep], a["void_type"][keep], [], [], a["waves"],
                                              a["octaves"], a["zones"], w.params.grid_cell_m, w._extra["ob_max"])
        g_u = _smooth_field(self._unmapped_arrays, P)
        g_m = _smooth_field(w.survey_world()._arrays, P)
        return float(np.mean(g_m >= g_u))


def _frame(T_map_scan: np.ndarray, levelled: bool, u: np.ndarray, tilt_sigma_deg: float) -> np.ndarray:
    """Output frame ``T_map_out`` at the scan origin: levelled (random heading, tilt error) or uniform SO(3)."""
    T = np.eye(4)
    T[:3, 3] = T_map_scan[:3, 3]
    if levelled:
        psi = 2.0 * math.pi * u[0]
        c, s = math.cos(psi), math.sin(psi)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        if tilt_sigma_deg > 0:
            ax = 2.0 * math.pi * u[1]
            # |N(0, sigma^2)| from two uniforms (Box-Muller)
            ang = math.radians(tilt_sigma_deg) * abs(math.sqrt(-2.0 * math.log(max(u[2], 1e-300)))
                                                     * math.cos(2.0 * math.pi * u[3]))
            R = _axis_angle(np.array([math.cos(ax), math.sin(ax), 0.0]), ang) @ R
    else:
        # Shoemake (1992): uniform unit quaternion from three uniforms
        u1, u2, u3 = u[4], 2.0 * math.pi * u[5], 2.0 * math.pi * u[6]
        a, b = math.sqrt(1.0 - u1), math.sqrt(u1)
        x, y, z, w = a * math.sin(u2), a * math.cos(u2), b * math.sin(u3), b * math.cos(u3)
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    T[:3, :3] = R
    return T


def _axis_angle(axis: np.ndarray, ang: float) -> np.ndarray:
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(ang) * K + (1.0 - math.cos(ang)) * (K @ K)


def make_study_world(roughness_m: float | None = None, twins: str = "none", unmapped: int = 0, seed: int = 0, *,
                     lining: str | None = None, n_levels: int = 2, level_spacing_m: float = 25.0,
                     map_passes: int = 1, vehicle: bool = True, base: str = "small") -> StudyWorld:
    """A world with the study options, its survey map and a scan drawer (:meth:`StudyWorld.draw_scans`).

    Parameters
    ----------
    roughness_m : float, optional
        ``WorldParams.wall_roughness_m``: std (m) of the wall-bump field (0.05 / 0.08 / 0.25 in
        the localization studies). None: the base preset's amplitudes (std 0.064 m) or the lining's default.
    twins : {"none", "exact", "near"}
        ``WorldParams.repeat_levels``.
    unmapped : int
        ``WorldParams.unmapped_headings``: headings present in the world, absent from the map.
    seed : int
        World seed; the map uses ``seed + 1`` (carrier) and ``seed + 2 ...`` (range noise).
    lining : {None, "blasted", "shotcrete"}
        ``WorldParams.lining``.
    n_levels, level_spacing_m : int, float
        Levels and their vertical spacing (m); 25 m by default (the paper preset's) so that exact
        copies are 25 m apart and the rough zones of one level do not reach the next.
    map_passes : int
        Survey passes of :func:`~minegeo.synth.dataset.build_survey_map` (1: a frame every 10 m).
    vehicle : bool
        Keep the parked vehicle (level 0, regular section) in the world and the map.
    base : str
        Preset whose other parameters are used (``"small"``).

    Returns
    -------
    StudyWorld
    """
    if base not in PRESETS:
        raise InputError(f"unknown base preset {base!r}; choose one of {sorted(PRESETS)}")
    params = replace(PRESETS[base], n_levels=int(n_levels), level_spacing_m=float(level_spacing_m),
                     wall_roughness_m=None if roughness_m is None else float(roughness_m), lining=lining,
                     repeat_levels=twins, unmapped_headings=int(unmapped))
    world = build_world("study" if base == "small" else f"study-{base}", int(seed), params=params)
    if not vehicle:
        world = world.with_vehicle(None)
    cloud = build_survey_map(world, seed=int(seed) + 1, passes=int(map_passes))
    opts = {"roughness_m": roughness_m, "twins": twins, "unmapped": int(unmapped), "seed": int(seed),
            "lining": lining, "n_levels": int(n_levels), "level_spacing_m": float(level_spacing_m),
            "map_passes": int(map_passes), "vehicle": bool(vehicle), "base": base}
    log.info("study world %s: %d drifts, map %d points", opts, len(world.drifts), len(cloud))
    return StudyWorld(world=world, map=cloud, options=opts)


# ---------------------------------------------------------------------- wall roughness
def sample_wall_points(world: MineWorld, n: int = 20000, seed: int = 0):
    """Points of the smooth design surface on walls and roofs of ordinary drift sections.

    Uniform over the wall (floor to ``wall_height_m``) and arch of every drift segment, kept
    where the design field is 0 (so not in junctions or roof fall-outs) and outside the rough
    zones' reach (3 r). Floors are not sampled.

    Returns
    -------
    points : (n, 3) ndarray
        On the design surface (m, world frame).
    normals : (n, 3) ndarray
        Outward unit normals of the design surface (into the rock).
    """
    a = world._arrays
    rng = np.random.default_rng(seed)
    seg = a["void_type"] == 0
    V = a["void_prims"][seg]
    L = np.linalg.norm(V[:, 3:5] - V[:, 0:2], axis=1)
    ok_seg = L > 1e-9
    V, L = V[ok_seg], L[ok_seg]
    pts, nrms, have = [], [], 0
    for _ in range(100):
        if have >= n:
            break
        m = 4 * n
        k = rng.choice(len(V), m, p=L / L.sum())
        u = rng.uniform(0.0, 1.0, m)
        A, B = V[k, 0:3], V[k, 3:6]
        c = A + u[:, None] * (B - A)
        t = (B[:, :2] - A[:, :2]) / L[k, None]
        left = np.column_stack([-t[:, 1], t[:, 0]])
        R, hw = V[k, 6], V[k, 7]
        wall = rng.uniform(0.0, 1.0, m) < (2 * hw) / (2 * hw + math.pi * R)
        sgn = np.where(rng.uniform(0.0, 1.0, m) < 0.5, -1.0, 1.0)
        h = rng.uniform(0.0, 1.0, m) * hw
        ang = rng.uniform(-0.5, 0.5, m) * math.pi  # arch angle from the vertical
        lat = np.where(wall, sgn * R, R * np.sin(ang))
        z = np.where(wall, h, hw + R * np.cos(ang))
        p = np.column_stack([c[:, :2] + lat[:, None] * left, c[:, 2] + z])
        nh = np.where(wall, sgn, np.sin(ang))
        nz = np.where(wall, 0.0, np.cos(ang))
        nv = np.column_stack([nh[:, None] * left, nz])
        g = world.sdf(p, with_noise=False, with_structures=False)
        keep = np.abs(g) < 1e-9
        for zc in a["zones"]:
            keep &= np.sum((p - zc[:3]) ** 2, axis=1) > 9.0 * zc[3] ** 2
        pts.append(p[keep])
        nrms.append(nv[keep])
        have += int(keep.sum())
    P, N = np.vstack(pts)[:n], np.vstack(nrms)[:n]
    return np.ascontiguousarray(P), np.ascontiguousarray(N / np.linalg.norm(N, axis=1, keepdims=True))


def measure_wall_roughness(world: MineWorld, n: int = 20000, seed: int = 0, n_rays: int = 4000) -> dict:
    """Measured std of the wall-bump field, to compare with ``WorldParams.wall_roughness_m``.

    Parameters
    ----------
    world : MineWorld
    n : int
        Wall points for the field measurement (:func:`sample_wall_points`).
    seed : int
        Seeds the sample.
    n_rays : int
        Of those, points also measured by ray casting (0: skip).

    Returns
    -------
    dict
        ``std_m`` / ``mean_m``: std and mean (m) of ``n(p) = f_rock(p) - g(p)`` (rough minus smooth
        design field, no structures) at design-surface points -- the deviation the roughness adds
        there; ``ray_std_m`` / ``ray_mean_m``: std and mean (m) of the surface displacement along the
        outward normal, from a ray cast 1 m inside the design surface (bare rock, 3 m range);
        ``predicted_std_m`` (:func:`~minegeo.synth.world.roughness_amplitudes`); ``n``, ``n_rays``.
    """
    from minegeo.synth.world import roughness_amplitudes

    P, N = sample_wall_points(world, n, seed)
    f_rough = world.sdf(P, with_noise=True, with_structures=False)
    f_smooth = world.sdf(P, with_noise=False, with_structures=False)
    dev = f_rough - f_smooth
    out = {"std_m": float(dev.std()), "mean_m": float(dev.mean()), "n": int(len(P)),
           "predicted_std_m": float(roughness_amplitudes(world.params)[2])}
    if n_rays:
        # rays only where the rock behind the design surface is solid for 1.1 m (design field = -depth):
        # elsewhere (about 6 % of wall points, at junction mouths) the ray runs on into the next opening
        clean = np.ones(len(P), bool)
        for depth in np.linspace(0.1, 1.1, 11):
            clean &= world.sdf(P + depth * N, with_noise=False, with_structures=False) < -depth + 1e-6
        idx = np.flatnonzero(clean)[: int(n_rays)]
        O = np.ascontiguousarray(P[idx] - N[idx] * 1.0)
        r = _cast_arrays(world._arrays, O, np.ascontiguousarray(N[idx]), 3.0,
                         float(min(world.params.trace_step_factor, world._arrays["step_factor"])), with_solids=False)
        disp = r[np.isfinite(r)] - 1.0
        out.update(ray_std_m=float(disp.std()), ray_mean_m=float(disp.mean()), n_rays=int(disp.size),
                   ray_clean_fraction=float(clean.mean()))
    return out
