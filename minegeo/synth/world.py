"""The synthetic mine: drift network, rough rock surface and structures as a signed distance field.

Field convention
----------------
``MineWorld.sdf(p)`` is **positive in free space (air), negative in rock or inside a
solid structure, and zero on the surface** (metres). It is

.. math::

    f(p) = \\min\\Big( \\underbrace{\\max_i g_i(p) + n(p)}_{\\text{rock}},\\;
                       \\min_j s_j(p) \\Big)

where ``g_i`` is the inner distance of void primitive *i* (horseshoe drift segments,
roof fall-out cavities, sump pits; the union of voids is a max), ``n`` the seeded
multi-scale roughness (blast overbreak >= 0 up to about 0.3 m plus cm texture) and
``s_j`` the exact distance to solid structure *j* (rock bolts, roof straps, pipes,
cables, ventilation duct, railings, the parked vehicle). The field is an exact
distance for the structures and a Lipschitz-bounded estimate (constant below about
2) for the rough rock, which is what sphere tracing needs (Hart 1996: a step of f / L never
crosses the surface of a field with Lipschitz constant L).

Drift profile (Baek et al. 2022, Sec. 3.1: tunnel width and height about 4.5 m,
rampway slope 6-8 degrees): flat floor, vertical walls up to ``wall_height_m`` and a
half-circle arched roof of radius ``width_m / 2``. A drift is a 3D centreline
polyline *on the floor*; each segment is swept with the profile, with rounded
(vertical-axis) caps at the vertices so bends and T/X/Y junctions are the union of
the segments. Far from all primitives (deeper than ~1 m into rock) the field is
clamped to -1.2 m; it stays exact in free space.

Modules
-------
This module holds :class:`MineWorld` and :func:`build_world`; the parameters and roughness model are in
:mod:`minegeo.synth.world_params`, the drift network in :mod:`minegeo.synth.world_layout`, the field's
primitives and tables in :mod:`minegeo.synth.world_primitives` (their public names are importable here).

References
----------
Hart, J. C. (1996). Sphere tracing: a geometric method for the antialiased ray tracing
of implicit surfaces. The Visual Computer 12(10), 527-545.
Baek, J., Park, J., Cho, S., Lee, C. (2022). 3D global localization in the underground
mine environment using mobile LiDAR mapping and point cloud registration. Sensors 22, 2873.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from minegeo._validate import as_points, as_transform, check_positive
from minegeo.errors import InputError
from minegeo.synth import _kernels as K
from minegeo.synth.world_layout import (
    HELIX_ACCESS_M,
    Drift,
    Intersection,
    _add_headings,
    _classify,
    _curve_and_parking,
    _layout,
    _layout_repeated,
)
from minegeo.synth.world_params import (
    LININGS,
    NEW_OPTION_DEFAULTS,
    PRESETS,
    WorldParams,
    _world_params,
    roughness_amplitudes,
    squash_variance,
)
from minegeo.synth.world_primitives import (
    MIN_STEP_M,
    _assemble,
    _noise_arrays,
    _solid_primitives,
    _vehicle_model,
    _void_primitives,
)

__all__ = ["WorldParams", "Drift", "Intersection", "MineWorld", "build_world", "PRESETS", "LININGS",
           "roughness_amplitudes", "squash_variance", "NEW_OPTION_DEFAULTS", "HELIX_ACCESS_M", "MIN_STEP_M"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class MineWorld:
    """A generated mine: geometry (drift graph), structures and the arrays of its field.

    Build with :meth:`MineWorld.build` / :func:`build_world`; the object is immutable
    (use :meth:`with_vehicle` to move the parked vehicle). Coordinates are the local
    *world* (= map) frame in metres: x east-ish, y north-ish, z up, the first level's
    floor at z = 0.

    Attributes
    ----------
    preset, seed : str, int
    params : WorldParams
    nodes : (m, 3) float64
        Junction / end points of the drift graph (floor level).
    drifts : tuple[Drift]
    intersections : tuple[Intersection]
    dead_ends : tuple[int]
        Node ids of degree 1.
    features : dict
        Named places used to pick scan sections: ``irregular_roof``, ``curve``, ``regular``,
        ``sump``, ``meshed`` (each ``{"drift": index, "s_m": arc length}``), the vehicle
        ``parking`` poses (4x4) and the ``ramp_slopes_deg`` actually built.
    T_world_vehicle : (4, 4) float64 or None
        Pose of the parked vehicle (None: no vehicle in the world).
    unmapped : tuple[int]
        Indices of drifts present in the world but absent from the survey map
        (:func:`~minegeo.synth.dataset.build_map` surveys :meth:`survey_world`, which lacks them):
        the ``WorldParams.unmapped_headings`` or drifts marked by :meth:`with_unmapped`.
    """

    preset: str
    seed: int
    params: WorldParams
    nodes: np.ndarray
    drifts: tuple
    intersections: tuple
    dead_ends: tuple
    features: dict
    T_world_vehicle: np.ndarray | None
    _arrays: dict = field(repr=False)
    unmapped: tuple = ()
    _extra: dict = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(cls, preset: str = "small", seed: int = 0, params: WorldParams | None = None) -> MineWorld:
        """Generate the mine of a preset (``"small"`` or ``"paper"``) for a seed; see :func:`build_world`."""
        return build_world(preset, seed, params=params)

    # ------------------------------------------------------------------ queries
    def sdf(self, points, with_noise: bool = True, with_structures: bool = True) -> np.ndarray:
        """Field value (m) at ``points`` (n, 3) in the world frame: > 0 air, < 0 rock/solid, 0 surface.

        ``with_noise=False`` gives the smooth design profile (no overbreak/texture),
        ``with_structures=False`` the bare rock.
        """
        P = as_points(points, "points", min_points=0)
        out = np.empty(P.shape[0])
        a = self._arrays
        K.sdf_many(P, a["grid_f"], a["grid_i"], a["void_prims"], a["void_type"], a["v_start"], a["v_items"],
                   a["solid_prims"], a["solid_type"], a["s_start"], a["s_items"], a["waves"], a["octaves"],
                   a["zones"], *self._vehicle_args(), bool(with_noise), bool(with_structures), out)
        return out

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners (m) of the box containing all the open space (with overbreak margin)."""
        return self._arrays["bounds_min"].copy(), self._arrays["bounds_max"].copy()

    @property
    def total_length_m(self) -> float:
        """Summed centreline length of all drifts (m)."""
        return float(sum(d.length_m for d in self.drifts))

    def adjacency(self) -> dict[int, list[tuple[int, int]]]:
        """Node -> list of (drift index, other node)."""
        adj: dict[int, list[tuple[int, int]]] = {i: [] for i in range(len(self.nodes))}
        for k, d in enumerate(self.drifts):
            adj[d.a].append((k, d.b))
            adj[d.b].append((k, d.a))
        return adj

    def n_independent_loops(self) -> int:
        """Cyclomatic number of the drift graph (edges - nodes + components): > 0 means loops exist."""
        find = _union_find(len(self.nodes), [(d.a, d.b) for d in self.drifts])
        comps = len({find(i) for i in range(len(self.nodes))})
        return len(self.drifts) - len(self.nodes) + comps

    def with_vehicle(self, T_world_vehicle) -> MineWorld:
        """The same world with the parked vehicle at ``T_world_vehicle`` (4x4), or removed (None)."""
        T = None if T_world_vehicle is None else as_transform(T_world_vehicle, "T_world_vehicle")
        return replace(self, T_world_vehicle=T)

    def cast(self, origins, directions, max_range_m: float, with_noise: bool = True,
             return_steps: bool = False):
        """Ranges (m) along unit ``directions`` from ``origins`` to the first surface; NaN = no return.

        Sphere tracing with bisection refinement to 1e-4 m (see ``_kernels.cast_rays``);
        the smallest step is ``MIN_STEP_M`` (5 mm). With ``return_steps`` also the number
        of marching steps per ray (a cost diagnostic).
        """
        O = as_points(origins, "origins", min_points=0)
        D = as_points(directions, "directions", min_points=0)
        if O.shape != D.shape:
            raise InputError(f"origins {O.shape} and directions {D.shape} must have the same shape")
        check_positive(max_range_m, "max_range_m")
        out = np.empty(O.shape[0])
        steps = np.empty(O.shape[0], np.int64)
        a = self._arrays
        K.cast_rays(O, D, float(max_range_m), float(min(self.params.trace_step_factor, a["step_factor"])),
                    MIN_STEP_M, 4000, 1e-4, a["grid_f"], a["grid_i"], a["void_prims"], a["void_type"],
                    a["v_start"], a["v_items"], a["solid_prims"], a["solid_type"], a["s_start"], a["s_items"],
                    a["waves"], a["octaves"], a["zones"], *self._vehicle_args(), bool(with_noise),
                    a["noise_min"], a["ob_factor"], out, steps)
        return (out, steps) if return_steps else out

    def _vehicle_args(self):
        a = self._arrays
        if self.T_world_vehicle is None:
            return np.eye(4), np.zeros((0, 8)), np.zeros(0, np.int64), np.zeros(4)
        T = self.T_world_vehicle
        Tinv = np.eye(4)
        Tinv[:3, :3] = T[:3, :3].T
        Tinv[:3, 3] = -T[:3, :3].T @ T[:3, 3]
        c = T[:3, :3] @ a["veh_centre"] + T[:3, 3]
        sphere = np.array([c[0], c[1], c[2], a["veh_radius"]])
        return np.ascontiguousarray(Tinv), a["veh_prims"], a["veh_type"], sphere

    @property
    def repeat(self) -> dict | None:
        """Repeated levels (``WorldParams.repeat_levels`` not ``"none"``): ``mode``, ``offset_m`` (the
        translation of one level, (0, 0, -level_spacing_m)), ``unit_edges`` and ``copies``
        ``{k: {unit drift: its copy on level k}}``; None otherwise."""
        return self._extra.get("repeat")

    def twins(self, drift: int) -> list[tuple[int, np.ndarray]]:
        """The copies of a drift on the other levels of a repeated-level world.

        Returns
        -------
        list of (drift index, offset)
            ``offset`` (3,) m maps a point of ``drift`` onto the same place of the copy
            (``p_copy = p + offset``); empty for worlds without repeated levels and for drifts that
            have no copy (the decline's last turn, headings).
        """
        rep = self.repeat
        if rep is None:
            return []
        dz = -float(rep["offset_m"][2])
        members: dict[int, int] = {}  # level -> drift
        for cm in rep["copies"].values():
            for u, c in cm.items():
                if drift in (u, c):
                    members = {0: u}
                    members.update({kk: cc[u] for kk, cc in rep["copies"].items() if u in cc})
                    break
            if members:
                break
        if not members:
            return []
        lev = next(k for k, e in members.items() if e == drift)
        return [(e, np.array([0.0, 0.0, -(k - lev) * dz])) for k, e in sorted(members.items()) if e != drift]

    def with_unmapped(self, drifts) -> MineWorld:
        """The same world with ``drifts`` (indices or names) also absent from the survey map.

        The mapped drifts must stay connected to node 0 (where the survey starts).

        Raises
        ------
        InputError
            Unknown drift, or the mapped drifts would no longer be connected.
        """
        names = {d.name: k for k, d in enumerate(self.drifts)}
        idx = set(self.unmapped)
        for x in drifts:
            if isinstance(x, str):
                if x not in names:
                    raise InputError(f"unknown drift {x!r}")
                idx.add(names[x])
            else:
                k = int(x)
                if not 0 <= k < len(self.drifts):
                    raise InputError(f"drift index {k} out of range 0..{len(self.drifts) - 1}")
                idx.add(k)
        find = _union_find(len(self.nodes), [(d.a, d.b) for k, d in enumerate(self.drifts) if k not in idx])
        mapped_nodes = {n for k, d in enumerate(self.drifts) if k not in idx for n in (d.a, d.b)}
        if any(find(n) != find(0) for n in mapped_nodes) or 0 not in mapped_nodes:
            raise InputError("the mapped drifts would not be connected to the survey start (node 0); "
                             "mark dead-end drifts only")
        extra = {k: v for k, v in self._extra.items() if k != "survey_arrays"}
        return replace(self, unmapped=tuple(sorted(idx)), _extra=extra)

    def survey_world(self) -> MineWorld:
        """The world as it was surveyed: without the void and the structures of the unmapped drifts.

        Their mouths are the rock walls (or the dead-end caps) of the drifts they leave. The world
        itself when nothing is unmapped. The drift list is unchanged (``unmapped`` still names the
        drifts the survey route must skip).
        """
        if not self.unmapped or self._extra.get("is_survey_world"):
            return self
        drop = np.array(sorted(self.unmapped), np.int64)
        kv = ~np.isin(self._extra["void_owner"], drop)
        ks = ~np.isin(self._extra["solid_owner"], drop)
        arr = self._extra.get("survey_arrays")  # cache: the arrays do not depend on the vehicle pose
        if arr is None:
            a = self._arrays
            arr = _assemble(a["void_prims"][kv], a["void_type"][kv], a["solid_prims"][ks], a["solid_type"][ks],
                            a["waves"], a["octaves"], a["zones"], self.params.grid_cell_m, self._extra["ob_max"])
            for k in ("veh_prims", "veh_type", "veh_centre", "veh_radius"):
                arr[k] = a[k]
            self._extra["survey_arrays"] = arr
        extra = {k: v for k, v in self._extra.items() if k != "survey_arrays"}
        extra.update(void_owner=self._extra["void_owner"][kv], solid_owner=self._extra["solid_owner"][ks],
                     is_survey_world=True)
        return replace(self, _arrays=arr, _extra=extra)

    def summary(self) -> dict:
        """Short JSON-able description (counts, lengths, intersection types)."""
        kinds: dict[str, float] = {}
        for d in self.drifts:
            kinds[d.kind] = kinds.get(d.kind, 0.0) + d.length_m
        types: dict[str, int] = {}
        for it in self.intersections:
            types[it.type] = types.get(it.type, 0) + 1
        return {
            "preset": self.preset,
            "seed": self.seed,
            "n_levels": self.params.n_levels,
            "n_drifts": len(self.drifts),
            "total_length_m": round(self.total_length_m, 3),
            "length_by_kind_m": {k: round(v, 3) for k, v in sorted(kinds.items())},
            "intersections_by_type": dict(sorted(types.items())),
            "n_dead_ends": len(self.dead_ends),
            "n_loops": self.n_independent_loops(),
            "ramp_slopes_deg": self.features["ramp_slopes_deg"],
            "n_void_primitives": int(self._arrays["void_prims"].shape[0]),
            "n_solid_primitives": int(self._arrays["solid_prims"].shape[0]),
            **self._study_summary(),
        }

    def _study_summary(self) -> dict:
        """Keys of the study options, present only when an option is used (old summaries unchanged)."""
        out: dict = {}
        p = self.params
        if p.wall_roughness_m is not None or p.lining is not None:
            ob, tex, std = self._extra.get("roughness") or roughness_amplitudes(p)
            out["roughness"] = {"lining": p.lining, "wall_roughness_std_m": round(std, 6),
                                "overbreak_m": [round(x, 6) for x in ob], "texture_m": [round(x, 6) for x in tex]}
        if self.repeat is not None:
            rep = self.repeat
            out["repeat_levels"] = {"mode": rep["mode"], "offset_m": rep["offset_m"],
                                    "helix_radius_m": round(rep["helix_radius_m"], 6),
                                    "n_twinned_drifts": int(sum(len(cm) for cm in rep["copies"].values()))}
        if self.unmapped:
            out["unmapped_drifts"] = [self.drifts[k].name for k in self.unmapped]
        return out


# ====================================================================== connectivity
def _union_find(n: int, pairs):
    """Joins nodes ``0..n-1`` along ``pairs``; returns ``find(i)``, the representative of node i's component."""
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in pairs:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
    return find


def build_world(preset: str = "small", seed: int = 0, params: WorldParams | None = None) -> MineWorld:
    """Generate a seeded, deterministic synthetic underground mine.

    Parameters
    ----------
    preset : {"small", "paper"}
        ``small``: two levels, ~0.6 km of drifts (tests, seconds). ``paper``: four levels,
        several km of drifts, comparable to the Gwan-in mine of Baek et al. (2022, Sec. 3.1).
    seed : int
        Every random choice (layout jitter, ramp slope in 6-8 degrees, roughness phases,
        structure placement, vehicle parking) derives from ``np.random.default_rng(seed)``.
    params : WorldParams, optional
        Overrides the preset's parameters.

    Returns
    -------
    MineWorld
        With a parked vehicle at ``features["parking"][0]``.

    Raises
    ------
    InputError
        Unknown preset or negative seed.
    """
    # the random draws happen in this order: layout, roof fall-outs, roughness, bolt angles
    params, seed = _world_params(preset, seed, params)
    rng = np.random.default_rng(seed)
    rep = None
    if params.repeat_levels == "none":
        g, feats = _layout(params, rng)
    else:
        g, feats, rep = _layout_repeated(params, rng)
    heads = _add_headings(g, params, seed) if params.unmapped_headings else []
    exact = rep is not None and rep["mode"] == "exact"
    void, zones, reg, pit = _void_primitives(g, feats, params, rep, rng)
    waves, octaves = _noise_arrays(params, rng, z_period_m=float(params.level_spacing_m) if exact else None)
    ob_eff, tex_eff, _ = roughness_amplitudes(params)
    ob_max = float(sum(ob_eff) * 2.0 + sum(tex_eff))
    base = _assemble(void.rows, void.types, [], [], waves, octaves, zones, params.grid_cell_m, ob_max)
    solid = _solid_primitives(g, feats, params, base, rep, reg, pit, rng)
    arrays = _assemble(void.rows, void.types, solid.rows, solid.types, waves, octaves, zones, params.grid_cell_m,
                       ob_max)
    vp, vt = _vehicle_model()
    arrays["veh_prims"], arrays["veh_type"] = np.ascontiguousarray(vp), np.ascontiguousarray(vt)
    arrays["veh_centre"] = np.array([0.3, 0.0, 1.2])
    arrays["veh_radius"] = 3.8
    parking = _curve_and_parking(g, feats, reg)
    feats["parking"] = parking
    intersections, dead = _classify(g)
    drifts = tuple(Drift(f"{kind}_L{lev}_{k:03d}", a, b, poly, kind, lev)
                   for k, (a, b, poly, kind, lev) in enumerate(g.edges))
    extra = {"void_owner": np.array(void.owners, np.int64), "solid_owner": np.array(solid.owners, np.int64),
             "ob_max": ob_max, "roughness": roughness_amplitudes(params)}
    if rep is not None:
        extra["repeat"] = rep
    world = MineWorld(preset=str(preset), seed=seed, params=params, nodes=np.array(g.nodes), drifts=drifts,
                      intersections=intersections, dead_ends=dead, features=feats,
                      T_world_vehicle=parking[0].copy(), _arrays=arrays, unmapped=tuple(heads), _extra=extra)
    log.info("synthetic mine %s seed %d: %d drifts, %.0f m, %d intersections, %d solids",
             preset, seed, len(drifts), world.total_length_m, len(intersections), len(solid.rows))
    return world
