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

References
----------
Hart, J. C. (1996). Sphere tracing: a geometric method for the antialiased ray tracing
of implicit surfaces. The Visual Computer 12(10), 527-545.
Baek, J., Park, J., Cho, S., Lee, C. (2022). 3D global localization in the underground
mine environment using mobile LiDAR mapping and point cloud registration. Sensors 22, 2873.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from functools import cache

import numpy as np

from minegeo._validate import as_points, as_transform, check_positive
from minegeo.errors import InputError
from minegeo.synth import _kernels as K

__all__ = ["WorldParams", "Drift", "Intersection", "MineWorld", "build_world", "PRESETS", "LININGS",
           "roughness_amplitudes", "squash_variance"]

log = logging.getLogger(__name__)

#: smallest sphere-tracing step (m): rock slivers thinner than this along a ray may be missed
#: (the thinnest structure is a cable of 2 cm radius); crossings are refined to 1e-4 m.
MIN_STEP_M = 0.005


@dataclass(frozen=True)
class WorldParams:
    """Parameters of the generated mine (all lengths in metres, angles in degrees).

    Attributes
    ----------
    n_levels : int
        Number of mining levels, joined in sequence by ramps.
    main_length_m : float
        Length of each level's main drift (haulage drive).
    crosscut_spacing_m : float
        Spacing of the cross-cuts between the main drift and the parallel drive.
    n_crosscuts : int
        Cross-cuts per level (>= 2 so the parallel drive closes loops).
    parallel_offset_m : float
        Horizontal distance between main drift and parallel drive.
    level_spacing_m : float
        Vertical distance between consecutive level floors.
    ramp_slope_deg : tuple(float, float)
        Range the seeded ramp slope is drawn from (the paper: 6-8 degrees).
    width_m, wall_height_m : float
        Drift width and wall height; the roof is a half circle, so the height is
        ``wall_height_m + width_m / 2`` (4.5 m by default).
    ring_radius_m : float
        Radius of the ring roadway (a loop) at the end of each level but the last.
    overbreak_m : tuple(float, float)
        Amplitudes of the two overbreak octaves (long ~6 m and medium ~1.5 m wavelength);
        their sum (0.28 m) is the maximum overbreak in ordinary sections.
    texture_m : tuple(float, float)
        Amplitudes of the signed texture octaves (~0.35 m and ~0.1 m wavelength).
    bolt_spacing_m : float
        Distance between rings of rock bolts along a drift.
    trace_step_factor : float
        Sphere-tracing step as a fraction of the field value (< 1 / Lipschitz bound).
    grid_cell_m : float
        Cell size of the acceleration grid.
    wall_roughness_m : float or None
        Target standard deviation (m) of the wall-bump field ``n(p)`` (overbreak + texture) over
        the ordinary rock surface (walls and roof of the drifts, outside the rough zones and the
        roof fall-outs). The two overbreak octaves are scaled by one common factor so that
        ``sqrt(c^2 sigma_ob^2 + sigma_tex^2)`` equals it (see :func:`roughness_amplitudes`);
        the texture octaves are kept. ``None`` (default): ``overbreak_m`` as given (std 0.064 m
        for the default amplitudes). Overbreak is >= 0, so its mean (half the summed amplitudes)
        grows with it: a 0.25 m std means about 0.55 m mean and 1.1 m maximum overbreak.
    lining : {None, "blasted", "shotcrete"}
        Spectrum preset (see :data:`LININGS`): ``"blasted"`` keeps the default octave shape
        with 0.25 m std; ``"shotcrete"`` damps the 1.5 m octave and the texture (sprayed
        concrete fills blast pockets and is smooth at the cm scale) with 0.065 m std.
        ``wall_roughness_m`` overrides the preset's std. ``None``: ``overbreak_m``/``texture_m``.
    repeat_levels : {"none", "exact", "near"}
        ``"none"`` (default): the layout described above. ``"exact"``: level k is an exact copy of
        level 0 translated by ``(0, 0, -k level_spacing_m)`` -- the same drifts, roughness
        (vertical wavenumbers quantised to multiples of ``2 pi / level_spacing_m``), roof fall-outs,
        sump pit, bolts, straps, services and railings -- and the levels are joined by a helical
        decline (one turn per level, beside the ring roadway) reached through a 10 m access drift.
        ``"near"``: the same layout (drift centrelines, sump pit, railings, rough zones) but
        independent roughness (the ordinary, non-periodic waves), roof fall-outs and bolt
        placement on every level. Needs ``n_levels >= 2`` and ``level_spacing_m >= 12``.
    unmapped_headings : int
        Number of development headings added to the world but absent from the survey map
        (:func:`~minegeo.synth.dataset.build_map` surveys a world without them): each continues a
        dead end straight for 12 m, bends by 60-90 degrees and runs on to ``heading_length_m``.
        Drawn from their own random stream, so the rest of the layout is that of the world without
        them. Their drift indices are ``MineWorld.unmapped``.
    heading_length_m : float
        Centreline length of each unmapped heading.
    """

    n_levels: int = 2
    main_length_m: float = 80.0
    crosscut_spacing_m: float = 32.0
    n_crosscuts: int = 3
    parallel_offset_m: float = 24.0
    level_spacing_m: float = 15.0
    ramp_slope_deg: tuple = (6.0, 8.0)
    width_m: float = 4.5
    wall_height_m: float = 2.25
    ring_radius_m: float = 14.0
    ramp_turn_radius_m: float = 15.0
    overbreak_m: tuple = (0.2, 0.08)
    texture_m: tuple = (0.015, 0.004)
    bolt_spacing_m: float = 1.5
    stubs_per_level: int = 0
    stub_length_m: float = 15.0
    trace_step_factor: float = 0.45
    grid_cell_m: float = 2.0
    wall_roughness_m: float | None = None
    lining: str | None = None
    repeat_levels: str = "none"
    unmapped_headings: int = 0
    heading_length_m: float = 60.0


#: Options added after the first release: left out of ``truth.json`` while at these defaults,
#: so worlds without them write the same bytes as before.
NEW_OPTION_DEFAULTS = {"wall_roughness_m": None, "lining": None, "repeat_levels": "none", "unmapped_headings": 0,
                       "heading_length_m": 60.0}

#: Lining presets: overbreak octave shape (6 m, 1.5 m; scaled to the std), texture amplitudes
#: (0.35 m, 0.1 m) and the default std of the wall-bump field (m).
LININGS: dict[str, dict] = {
    "blasted": {"overbreak_shape": (0.2, 0.08), "texture_m": (0.015, 0.004), "std_m": 0.25},
    "shotcrete": {"overbreak_shape": (0.2, 0.03), "texture_m": (0.004, 0.001), "std_m": 0.065},
}

#: Waves per octave (6 m, 1.5 m, 0.35 m, 0.1 m), as built by ``_noise_arrays``.
_OCTAVE_WAVES = (8, 8, 8, 6)


@cache
def squash_variance(n_waves: int) -> float:
    """Variance of ``q = S / sqrt(1 + S^2)`` for ``S = sqrt(2/N) sum_k sin(theta_k)``, theta_k iid uniform.

    ``E[q] = 0`` by symmetry and ``Var q = 1 - E[1 / (1 + S^2)]`` with
    ``E[1 / (1 + S^2)] = int_0^inf exp(-u) J0(u sqrt(2/N))^N du`` (the Laplace transform of the
    characteristic function ``J0(u sqrt(2/N))^N`` of S). 0.34880 for N = 8, 0.35033 for N = 6
    (a 2e7-sample Monte Carlo agrees to 1e-4). Over a drift surface the random-phase plane waves
    of an octave behave as independent uniform phases, which is what makes the measured wall
    std match :func:`roughness_amplitudes` (docs/synth.md).
    """
    from scipy.integrate import quad
    from scipy.special import j0

    c = math.sqrt(2.0 / n_waves)
    val, _ = quad(lambda u: math.exp(-u) * j0(c * u) ** n_waves, 0.0, 80.0, limit=500, epsabs=1e-14)
    return 1.0 - val


def _octave_std(overbreak_m, texture_m) -> tuple[float, float]:
    """(std of the overbreak part, std of the texture part) of the bump field outside rough zones (m)."""
    v8, v6 = squash_variance(_OCTAVE_WAVES[0]), squash_variance(_OCTAVE_WAVES[3])
    var_ob = sum((a / 2.0) ** 2 * squash_variance(n) for a, n in zip(overbreak_m, _OCTAVE_WAVES[:2], strict=True))
    var_tex = texture_m[0] ** 2 * v8 + texture_m[1] ** 2 * v6
    return math.sqrt(var_ob), math.sqrt(var_tex)


def roughness_amplitudes(p: WorldParams) -> tuple[tuple, tuple, float]:
    """Octave amplitudes (m) a world built with ``p`` uses, and the std (m) of its wall-bump field.

    The bump field is ``n = sum_o a_o (1 + q_o) / 2`` over the two overbreak octaves plus
    ``sum_o a_o q_o`` over the two texture octaves, with independent squashed random-phase sums
    ``q_o`` of variance :func:`squash_variance`; so ``std(n)^2 = sum_ob (a/2)^2 v + sum_tex a^2 v``.
    With ``wall_roughness_m`` (or a ``lining``), the overbreak shape is scaled by
    ``c = sqrt(std^2 - sigma_tex^2) / sigma_ob(shape)``.

    Returns
    -------
    overbreak_m : (2,) tuple
        Amplitudes of the 6 m and 1.5 m overbreak octaves (m).
    texture_m : (2,) tuple
        Amplitudes of the 0.35 m and 0.1 m texture octaves (m).
    std_m : float
        Predicted std of the bump field over ordinary rock surfaces (m); e.g. 0.0643 m for the
        default amplitudes (0.2, 0.08, 0.015, 0.004).

    Raises
    ------
    InputError
        Unknown lining, or a requested std not above the texture's own std.
    """
    if p.lining is None and p.wall_roughness_m is None:
        ob, tex = tuple(p.overbreak_m), tuple(p.texture_m)
        s_ob, s_tex = _octave_std(ob, tex)
        return ob, tex, math.hypot(s_ob, s_tex)
    if p.lining is not None:
        if p.lining not in LININGS:
            raise InputError(f"unknown lining {p.lining!r}; choose one of {sorted(LININGS)}")
        lin = LININGS[p.lining]
        shape, tex, target = lin["overbreak_shape"], tuple(lin["texture_m"]), lin["std_m"]
    else:
        shape, tex, target = tuple(p.overbreak_m), tuple(p.texture_m), None
    if p.wall_roughness_m is not None:
        target = float(p.wall_roughness_m)
    s_ob, s_tex = _octave_std(shape, tex)
    if not (math.isfinite(target) and target > s_tex * 1.0001) or s_ob <= 0:
        raise InputError(f"wall_roughness_m must exceed the texture's own std {s_tex:.4f} m, got {target!r}")
    c = math.sqrt(target * target - s_tex * s_tex) / s_ob
    return (shape[0] * c, shape[1] * c), tex, target


def _check_params(p: WorldParams) -> None:
    """Validate the optional study options of ``p`` (the classic fields are validated where used)."""
    if p.repeat_levels not in ("none", "exact", "near"):
        raise InputError(f"repeat_levels must be 'none', 'exact' or 'near', got {p.repeat_levels!r}")
    if p.repeat_levels != "none":
        if p.n_levels < 2:
            raise InputError("repeat_levels needs n_levels >= 2")
        if not p.level_spacing_m >= 12.0:
            raise InputError(f"repeat_levels needs level_spacing_m >= 12 (helical decline), got {p.level_spacing_m}")
    if isinstance(p.unmapped_headings, bool) or not isinstance(p.unmapped_headings, (int, np.integer)) \
            or p.unmapped_headings < 0:
        raise InputError(f"unmapped_headings must be an integer >= 0, got {p.unmapped_headings!r}")
    if p.unmapped_headings and not p.heading_length_m >= 30.0:
        raise InputError(f"heading_length_m must be >= 30, got {p.heading_length_m}")
    roughness_amplitudes(p)


#: Named presets: ``small`` (seconds, for tests) and ``paper`` (several km, map ~1e7 points).
PRESETS: dict[str, WorldParams] = {
    "small": WorldParams(),
    "paper": WorldParams(
        n_levels=4,
        main_length_m=520.0,
        crosscut_spacing_m=52.0,
        n_crosscuts=10,
        parallel_offset_m=40.0,
        level_spacing_m=25.0,
        ring_radius_m=16.0,
        ramp_turn_radius_m=22.0,
        stubs_per_level=8,
        stub_length_m=22.0,
    ),
}


@dataclass(frozen=True, eq=False)
class Drift:
    """One drift (edge of the network): a floor centreline polyline from node ``a`` to ``b``.

    ``kind`` is one of ``main``, ``parallel``, ``crosscut``, ``branch``, ``ring``, ``ramp``,
    ``stub``; ``level`` is the level index (a ramp belongs to its upper level).
    """

    name: str
    a: int
    b: int
    centreline: np.ndarray
    kind: str
    level: int

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.centreline, axis=0), axis=1).sum())


@dataclass(frozen=True)
class Intersection:
    """A junction of three or more drifts: ``type`` is ``"T"``, ``"X"`` or ``"Y"``."""

    node: int
    position: tuple
    type: str
    degree: int
    level: int


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


# ====================================================================== layout
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


def _wiggle(P: np.ndarray, rng: np.random.Generator, amp_m: float) -> np.ndarray:
    """Add a smooth seeded lateral meander (zero at both ends) to a straight polyline."""
    if amp_m <= 0 or len(P) < 3:
        return P
    d = P[-1, :2] - P[0, :2]
    L = float(np.linalg.norm(d))
    if L < 1e-9:
        return P
    n = np.array([-d[1], d[0]]) / L
    s = np.linspace(0.0, 1.0, len(P))
    off = np.zeros(len(P))
    for k in (1, 2, 3):
        off += rng.uniform(-1, 1) * amp_m / k * np.sin(k * np.pi * s)
    Q = P.copy()
    Q[:, :2] += off[:, None] * n[None, :]
    return Q


def _straight(a, b, step_m: float = 2.0) -> np.ndarray:
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    L = float(np.linalg.norm(b[:2] - a[:2]))
    n = max(1, int(math.ceil(L / step_m)))
    s = np.linspace(0.0, 1.0, n + 1)[:, None]
    return a[None, :] * (1 - s) + b[None, :] * s


def _arc(centre, radius, ang0, ang1, z0, z1, step_m: float = 2.0) -> np.ndarray:
    L = abs(ang1 - ang0) * radius
    n = max(2, int(math.ceil(L / step_m)))
    t = np.linspace(0.0, 1.0, n + 1)
    ang = ang0 + (ang1 - ang0) * t
    return np.column_stack([centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang), z0 + (z1 - z0) * t])


class _Graph:
    def __init__(self):
        self.nodes: list[np.ndarray] = []
        self.edges: list[tuple[int, int, np.ndarray, str, int]] = []

    def node(self, xyz) -> int:
        self.nodes.append(np.asarray(xyz, float).copy())
        return len(self.nodes) - 1

    def edge(self, a: int, b: int, poly: np.ndarray, kind: str, level: int) -> int:
        poly = np.asarray(poly, float).copy()
        poly[0] = self.nodes[a]
        poly[-1] = self.nodes[b]
        self.edges.append((a, b, poly, kind, level))
        return len(self.edges) - 1


def _level_drifts(g: _Graph, feats: dict, p: WorldParams, rng: np.random.Generator, lev: int, last: bool,
                  start: int, sx: float, y_level: float) -> int:
    """The drifts of one level (main, parallel drive, cross-cuts, X, stubs, Y branch); returns the main's end node."""
    A = g.nodes[start]
    z = A[2]
    Lm = p.main_length_m * (1.0 + rng.uniform(-0.04, 0.04)) * (0.65 if last and p.n_levels > 1 else 1.0)
    ncc = max(2, p.n_crosscuts if not last else max(2, p.n_crosscuts // 2))
    span = Lm - 2 * p.crosscut_spacing_m / 3 if ncc > 1 else Lm / 2
    base = np.linspace(p.crosscut_spacing_m / 3.0, p.crosscut_spacing_m / 3.0 + span * 0.85, ncc)
    cc_x = np.sort(base + rng.uniform(-2.0, 2.0, ncc))
    x_cross = int(ncc // 2)  # this cross-cut continues to the far side: X junction
    y_x = 0.5 * (cc_x[0] + cc_x[1]) + rng.uniform(-2.0, 2.0)  # Y branch between the first two
    stub_x = []
    if p.stubs_per_level:
        stub_x = list(np.linspace(cc_x[1] + 0.5 * p.crosscut_spacing_m, cc_x[-1] - 0.5 * p.crosscut_spacing_m,
                                  p.stubs_per_level))
    marks = sorted([(x, "cc", i) for i, x in enumerate(cc_x)] + [(y_x, "y", 0)]
                   + [(x, "stub", i) for i, x in enumerate(stub_x)])
    prev = start
    main_nodes = {}
    side = -1.0  # parallel drive on the -y side; X extension, Y branch and stubs on the +y side
    for x, what, i in marks + [(Lm, "end", 0)]:
        nid = g.node([A[0] + sx * x, y_level, z])
        poly = _wiggle(_straight(g.nodes[prev], g.nodes[nid]), rng, 0.6)
        g.edge(prev, nid, poly, "main", lev)
        main_nodes[(what, i)] = nid
        prev = nid
    end_node = prev
    # parallel drive and cross-cuts
    par_nodes = []
    for i, x in enumerate(cc_x):
        mn = main_nodes[("cc", i)]
        pn = g.node([A[0] + sx * x + rng.uniform(-1.5, 1.5), y_level + side * p.parallel_offset_m, z])
        g.edge(mn, pn, _wiggle(_straight(g.nodes[mn], g.nodes[pn]), rng, 0.4), "crosscut", lev)
        par_nodes.append(pn)
        if i == x_cross:
            xn = g.node([A[0] + sx * x, y_level - side * 12.0, z])
            g.edge(mn, xn, _straight(g.nodes[mn], g.nodes[xn]), "crosscut", lev)
    for i in range(len(par_nodes) - 1):
        a, b = par_nodes[i], par_nodes[i + 1]
        g.edge(a, b, _wiggle(_straight(g.nodes[a], g.nodes[b]), rng, 0.8), "parallel", lev)
    # stubs (stope accesses) on the far side
    for i, x in enumerate(stub_x):
        mn = main_nodes[("stub", i)]
        sn = g.node([A[0] + sx * x + rng.uniform(-2, 2), y_level - side * p.stub_length_m, z])
        g.edge(mn, sn, _straight(g.nodes[mn], g.nodes[sn]), "stub", lev)
    # Y branch: leaves the main drift at ~40 degrees, gently curved, dead end with a sump
    mn = main_nodes[("y", 0)]
    ang = math.radians(rng.uniform(35.0, 45.0))
    Lb = 26.0
    hdg = np.array([-sx * math.cos(ang), -side * math.sin(ang)])  # back towards the level start
    mid = g.nodes[mn][:2] + hdg * Lb * 0.5
    hdg2 = np.array([-sx * math.cos(ang * 1.6), -side * math.sin(ang * 1.6)])
    endp = mid + hdg2 * Lb * 0.5
    bn = g.node([endp[0], endp[1], z])
    poly = np.vstack([_straight(g.nodes[mn], [mid[0], mid[1], z], 2.0)[:-1],
                      _straight([mid[0], mid[1], z], g.nodes[bn], 2.0)])
    ybranch = g.edge(mn, bn, poly, "branch", lev)
    if feats["sump"] is None:
        feats["sump"] = {"drift": ybranch, "level": lev}
    return end_node


def _ring_roadway(g: _Graph, p: WorldParams, end_node: int, sx: float, lev: int) -> int:
    """Ring roadway (two half circles, a loop) beyond the main drift's end; returns its far node."""
    Rr = p.ring_radius_m
    E = g.nodes[end_node]
    z = E[2]
    C = E[:2] + np.array([sx * Rr, 0.0])
    F = g.node([C[0] + sx * Rr, C[1], z])
    a0 = math.pi if sx > 0 else 0.0
    g.edge(end_node, F, _arc(C, Rr, a0, a0 - math.pi * (1 if sx > 0 else -1), z, z), "ring", lev)
    g.edge(end_node, F, _arc(C, Rr, a0, a0 + math.pi * (1 if sx > 0 else -1), z, z), "ring", lev)
    return F


def _layout(p: WorldParams, rng: np.random.Generator):
    """Seeded drift graph: levels of main drift + parallel drive + cross-cuts (loops), an
    X cross-cut, a Y branch ending in a sump, a ring roadway, stubs, and ramps between levels."""
    g = _Graph()
    feats: dict = {"ramp_slopes_deg": [], "sump": None}
    start = g.node([0.0, 0.0, 0.0])
    sx = 1.0
    y_level = 0.0
    for lev in range(p.n_levels):
        z = g.nodes[start][2]
        last = lev == p.n_levels - 1
        end_node = _level_drifts(g, feats, p, rng, lev, last, start, sx, y_level)
        if last:
            break
        # ring roadway (a loop) beyond the end of the main drift, then the ramp down
        F = _ring_roadway(g, p, end_node, sx, lev)
        slope = math.radians(rng.uniform(*p.ramp_slope_deg))
        feats["ramp_slopes_deg"].append(math.degrees(slope))
        dz = p.level_spacing_m
        Lr = dz / math.tan(slope)
        Rt = p.ramp_turn_radius_m
        Fp = g.nodes[F]
        l1 = 12.0
        l_arc = math.pi * Rt
        l3 = Lr - l1 - l_arc
        if l3 < 5.0:
            raise InputError("level spacing too small for the ramp geometry")
        z1 = z - dz * l1 / Lr
        z2 = z - dz * (l1 + l_arc) / Lr
        P1 = np.array([Fp[0] + sx * l1, Fp[1], z1])
        seg1 = _straight(Fp, P1)
        Ct = np.array([P1[0], P1[1] - Rt])
        th0 = math.pi / 2
        th1 = th0 - sx * math.pi  # turn towards -y and back
        seg2 = _arc(Ct, Rt, th0, th1, z1, z2)
        P3 = np.array([P1[0] - sx * l3, P1[1] - 2 * Rt, z - dz])
        seg3 = _straight(seg2[-1], P3)
        ramp_poly = np.vstack([seg1[:-1], seg2[:-1], seg3])
        nxt = g.node(P3)
        g.edge(F, nxt, ramp_poly, "ramp", lev)
        start = nxt
        y_level = P3[1]
        sx = -sx
    return g, feats


#: length (m) of the access drift from the ring roadway to the helical decline (repeated levels)
HELIX_ACCESS_M = 10.0


def _layout_repeated(p: WorldParams, rng: np.random.Generator):
    """Drift graph of repeated levels: level 0 (as in :func:`_layout`, with its ring roadway and a
    10 m access drift) copied to every level k translated by ``(0, 0, -k dz)``, the levels joined by a
    helical decline of one turn per level (radius ``dz / (2 pi tan slope)``, tangent to the access
    drift's end, which is a T junction on the middle levels).

    Returns ``(graph, features, repeat)`` where ``repeat`` holds ``offset_m`` (the translation of
    one level), ``unit_edges`` (edges of level 0 plus the first decline turn) and ``copies``
    ``{k: {unit edge: its copy on level k}}``.
    """
    g = _Graph()
    feats: dict = {"ramp_slopes_deg": [], "sump": None}
    start = g.node([0.0, 0.0, 0.0])
    end_node = _level_drifts(g, feats, p, rng, 0, False, start, 1.0, 0.0)
    F = _ring_roadway(g, p, end_node, 1.0, 0)
    slope = math.radians(rng.uniform(*p.ramp_slope_deg))
    dz = float(p.level_spacing_m)
    n = int(p.n_levels)
    Fp = g.nodes[F]
    q0 = g.node(Fp + np.array([HELIX_ACCESS_M, 0.0, 0.0]))
    g.edge(F, q0, _straight(Fp, g.nodes[q0]), "crosscut", 0)
    unit_nodes = list(range(len(g.nodes)))
    unit_edges = list(range(len(g.edges)))
    qnode = {0: q0}
    copies: dict[int, dict[int, int]] = {}
    for k in range(1, n):
        off = np.array([0.0, 0.0, -k * dz])
        nm = {i: g.node(g.nodes[i] + off) for i in unit_nodes}
        copies[k] = {e: g.edge(nm[g.edges[e][0]], nm[g.edges[e][1]], g.edges[e][2] + off, g.edges[e][3], k)
                     for e in unit_edges}
        qnode[k] = nm[q0]
    Rh = dz / (2.0 * math.pi * math.tan(slope))
    C = g.nodes[q0][:2] + np.array([Rh, 0.0])
    turn = _arc(C, Rh, math.pi, 3.0 * math.pi, 0.0, -dz)
    h0 = -1
    for k in range(n - 1):
        e = g.edge(qnode[k], qnode[k + 1], turn + np.array([0.0, 0.0, -k * dz]), "ramp", k)
        if k == 0:
            h0 = e
        else:
            copies[k][h0] = e
    feats["ramp_slopes_deg"] = [math.degrees(slope)] * (n - 1)
    rep = {"mode": p.repeat_levels, "offset_m": [0.0, 0.0, -dz], "unit_edges": unit_edges + [h0],
           "copies": copies, "helix_radius_m": Rh}
    return g, feats, rep


def _heading_poly(P0, d_in, leg1_m: float, bend_deg: float, total_m: float, radius_m: float = 8.0) -> np.ndarray:
    """Floor centreline of a heading: straight ``leg1_m`` along ``d_in``, an arc turning by ``bend_deg``
    (positive: to the left), then straight to a total length of ``total_m`` (all horizontal)."""
    P0 = np.asarray(P0, float)
    d = np.array([d_in[0], d_in[1]]) / np.hypot(d_in[0], d_in[1])
    P1 = P0 + np.array([*(d * leg1_m), 0.0])
    sgn = 1.0 if bend_deg > 0 else -1.0
    nrm = sgn * np.array([-d[1], d[0]])
    C = P1[:2] + nrm * radius_m
    a0 = math.atan2(P1[1] - C[1], P1[0] - C[0])
    b = math.radians(abs(bend_deg))
    arc = _arc(C, radius_m, a0, a0 + sgn * b, P0[2], P0[2])
    c, s_ = math.cos(sgn * b), math.sin(sgn * b)
    d2 = np.array([c * d[0] - s_ * d[1], s_ * d[0] + c * d[1]])
    leg3 = total_m - leg1_m - radius_m * b
    P3 = arc[-1] + np.array([*(d2 * leg3), 0.0])
    return np.vstack([_straight(P0, P1)[:-1], arc[:-1], _straight(arc[-1], P3)])


def _seg_dist_2d(P, A, B):
    """Horizontal distances (len(P), len(A)) from points P to segments A-B."""
    d = B[None, :, :2] - A[None, :, :2]
    L2 = np.maximum(np.sum(d * d, axis=2), 1e-12)
    u = np.clip(np.sum((P[:, None, :2] - A[None, :, :2]) * d, axis=2) / L2, 0.0, 1.0)
    q = A[None, :, :2] + u[..., None] * d - P[:, None, :2]
    return np.sqrt(np.sum(q * q, axis=2))


def _add_headings(g: _Graph, p: WorldParams, seed: int) -> list[int]:
    """Append ``p.unmapped_headings`` headings continuing dead ends (not the sump branches).

    Drawn from ``np.random.default_rng([seed, 0x4EAD])``. A candidate is kept when every
    centreline point beyond its first ``2 R + 4`` m is at least ``2 R + 3`` m (horizontally) from every other
    drift segment within ``H + 3`` m of its height; otherwise another bend, then another dead end
    is tried. Returns the new edge indices (kind ``"heading"``).
    """
    rng = np.random.default_rng([int(seed), 0x4EAD])
    R = p.width_m / 2.0
    H = p.wall_height_m + R
    deg = np.zeros(len(g.nodes), int)
    inc: dict[int, tuple[int, np.ndarray]] = {}
    for k, (a, b, poly, kind, _lev) in enumerate(g.edges):
        deg[a] += 1
        deg[b] += 1
        if kind != "branch":  # the sump branches keep their dead end
            inc[a] = (k, poly[min(2, len(poly) - 1), :2] - poly[0, :2])
            inc[b] = (k, poly[max(-3, -len(poly)), :2] - poly[-1, :2])
    cands = [i for i in range(len(g.nodes)) if deg[i] == 1 and i in inc
             and g.edges[inc[i][0]][3] != "branch"]
    out: list[int] = []
    for ci in rng.permutation(len(cands)):
        if len(out) == p.unmapped_headings:
            break
        node = cands[int(ci)]
        k_par, d_back = inc[node]
        d_in = -d_back / max(np.linalg.norm(d_back), 1e-12)
        segs = [(poly[:-1], poly[1:]) for (_a, _b, poly, _k, _l) in g.edges]
        A = np.vstack([s[0] for s in segs])
        B = np.vstack([s[1] for s in segs])
        zmid = 0.5 * (A[:, 2] + B[:, 2])
        for _ in range(6):
            bend = rng.uniform(60.0, 90.0) * (1.0 if rng.uniform() < 0.5 else -1.0)
            poly = _heading_poly(g.nodes[node], d_in, 12.0, bend, p.heading_length_m)
            Q = _densify_2d(poly, 1.0)
            s_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(Q[:, :2], axis=0), axis=1))])
            Q = Q[s_arc > 2 * R + 4.0]  # the mouth is where it meets its parent
            near_z = np.abs(zmid - g.nodes[node][2]) < H + 3.0
            if not near_z.any() or _seg_dist_2d(Q, A[near_z], B[near_z]).min() >= 2 * R + 3.0:
                out.append(g.edge(node, g.node(poly[-1]), poly, "heading", g.edges[k_par][4]))
                break
    if len(out) < p.unmapped_headings:
        raise InputError(f"only {len(out)} of {p.unmapped_headings} unmapped headings fit in this layout "
                         f"(each continues a dead end; {len(cands)} candidates)")
    return out


def _densify_2d(P: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` (or closer) along a polyline, vertices included."""
    out = [P[:1]]
    for a, b in zip(P[:-1], P[1:], strict=True):
        m = max(1, int(math.ceil(np.linalg.norm(b - a) / step_m)))
        out.append(a[None] + (b - a)[None] * (np.arange(1, m + 1) / m)[:, None])
    return np.vstack(out)


def _classify(g: _Graph):
    """Intersections (degree >= 3) typed T/X/Y from the directions the drifts leave the node."""
    inc: dict[int, list[np.ndarray]] = {i: [] for i in range(len(g.nodes))}
    for a, b, poly, _k, _l in g.edges:
        da = poly[min(2, len(poly) - 1), :2] - poly[0, :2]
        db = poly[max(-3, -len(poly)), :2] - poly[-1, :2]
        inc[a].append(da / np.linalg.norm(da))
        inc[b].append(db / np.linalg.norm(db))
    out, dead = [], []
    for i, dirs in inc.items():
        deg = len(dirs)
        if deg == 1:
            dead.append(i)
        if deg < 3:
            continue
        if deg >= 4:
            typ = "X"
        else:
            typ = "Y"
            for u in range(3):
                for v in range(u + 1, 3):
                    if np.dot(dirs[u], dirs[v]) < -0.94:  # collinear pair (within ~20 deg)
                        w = 3 - u - v
                        c = abs(float(np.dot(dirs[w], dirs[u])))
                        typ = "T" if c < 0.5 else "Y"  # third leg within 60-120 deg: T
        level = 0
        for a, b, _p, _k, lev in g.edges:
            if i in (a, b):
                level = lev
                break
        out.append(Intersection(i, tuple(float(x) for x in g.nodes[i]), typ, deg, level))
    return tuple(out), tuple(dead)


# ====================================================================== primitives
def _noise_arrays(p: WorldParams, rng: np.random.Generator, z_period_m: float | None = None):
    """Plane waves and octave table of the roughness (see ``_kernels``), amplitudes from
    :func:`roughness_amplitudes`. With ``z_period_m`` every wave's vertical wavenumber is moved to
    the nearest multiple of ``2 pi / z_period_m`` (its horizontal part rescaled to keep ``|k|``), so
    the field is periodic in z with that period (exact copies of levels); the draws are the same."""
    ob, tex, _ = roughness_amplitudes(p)
    specs = [  # (wavelength m, amplitude m, mode, n waves)
        (6.0, ob[0], 0, _OCTAVE_WAVES[0]),
        (1.5, ob[1], 0, _OCTAVE_WAVES[1]),
        (0.35, tex[0], 1, _OCTAVE_WAVES[2]),
        (0.1, tex[1], 1, _OCTAVE_WAVES[3]),
    ]
    waves, octs, k0 = [], [], 0
    for lam, amp, mode, n in specs:
        v = rng.normal(size=(n, 3))
        v[:, 2] *= 0.8
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        kmag = 2 * np.pi / lam * rng.uniform(0.8, 1.25, n)
        ph = rng.uniform(0, 2 * np.pi, n)
        w = v * kmag[:, None]
        if z_period_m is not None:
            w = _quantise_kz(w, kmag, 2 * np.pi / z_period_m)
        waves.append(np.column_stack([w, ph]))
        octs.append([k0, n, amp, mode])
        k0 += n
    return np.ascontiguousarray(np.vstack(waves)), np.ascontiguousarray(np.array(octs, float))


def _quantise_kz(w: np.ndarray, kmag: np.ndarray, dk: float) -> np.ndarray:
    """Wave vectors with k_z on multiples of ``dk`` (|k_z| < |k|) and the horizontal part rescaled to keep |k|."""
    out = w.copy()
    for i in range(w.shape[0]):
        m = int(round(w[i, 2] / dk))
        while m != 0 and abs(m * dk) >= kmag[i]:
            m -= 1 if m > 0 else -1
        kz = m * dk
        h = math.hypot(w[i, 0], w[i, 1])
        kh = math.sqrt(kmag[i] ** 2 - kz * kz)
        if h > 1e-12:
            out[i, 0], out[i, 1] = w[i, 0] * kh / h, w[i, 1] * kh / h
        else:
            out[i, 0], out[i, 1] = kh, 0.0
        out[i, 2] = kz
    return out


def _frames(poly: np.ndarray):
    """Per-segment unit horizontal tangent and left normal of a polyline."""
    d = np.diff(poly[:, :2], axis=0)
    L = np.linalg.norm(d, axis=1)
    t = d / L[:, None]
    n = np.column_stack([-t[:, 1], t[:, 0]])
    return t, n, L


def _resample(poly: np.ndarray, step_m: float):
    """Points every ``step_m`` of horizontal arc length along a polyline, with tangent/normal."""
    t, n, L = _frames(poly)
    cum = np.concatenate([[0.0], np.cumsum(L)])
    s = np.arange(step_m / 2, cum[-1] - 1e-9, step_m)
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(L) - 1)
    u = (s - cum[k]) / L[k]
    P = poly[k] * (1 - u)[:, None] + poly[k + 1] * u[:, None]
    return P, t[k], n[k], s


def _offset_polyline(poly: np.ndarray, lateral_m: float, height_m: float) -> np.ndarray:
    """Polyline offset sideways (mitred at vertices) and raised: for pipes, cables, the duct."""
    t, n, _ = _frames(poly)
    nv = np.zeros((len(poly), 2))
    nv[0], nv[-1] = n[0], n[-1]
    for i in range(1, len(poly) - 1):
        m = n[i - 1] + n[i]
        m /= np.linalg.norm(m)
        nv[i] = m / max(0.5, float(np.dot(m, n[i])))
    Q = poly.copy()
    Q[:, :2] += lateral_m * nv
    Q[:, 2] += height_m
    return Q


def _capsule_chain(Q: np.ndarray, r: float) -> list:
    return [[*Q[i], *Q[i + 1], r, 0.0] for i in range(len(Q) - 1)]


def _vehicle_model():
    """A parked utility vehicle / loader in its own frame (x forward, z up, origin on the floor)."""
    boxes = [
        [0.0, 0.0, 0.95, 2.4, 0.95, 0.45, 0.0],  # chassis
        [-1.2, -0.4, 1.95, 0.7, 0.5, 0.55, 0.0],  # cab (on the side away from the wall)
        [2.95, 0.0, 0.55, 0.35, 1.05, 0.4, 0.0],  # bucket
        [-2.1, 0.0, 1.55, 0.3, 0.8, 0.2, 0.0],  # engine cover
    ]
    prims = [[*b, 0.0] for b in boxes]
    types = [1] * len(boxes)
    for x in (-1.5, 1.5):
        prims.append([x, -0.55, 0.6, x, 0.55, 0.6, 0.6, 0.0])  # wheel axles as capsules
        types.append(0)
    return np.array(prims, float), np.array(types, np.int64)


def _build_grid(bmin, bmax, cell, void_boxes, solid_boxes, margin):
    dims = np.maximum(1, np.ceil((bmax - bmin) / cell).astype(np.int64))
    ncell = int(np.prod(dims))

    def csr(boxes):
        lists_c, lists_i = [], []
        for i, (lo, hi) in enumerate(boxes):
            i0 = np.clip(np.floor((lo - margin - bmin) / cell).astype(np.int64), 0, dims - 1)
            i1 = np.clip(np.floor((hi + margin - bmin) / cell).astype(np.int64), 0, dims - 1)
            ix, iy, iz = np.meshgrid(np.arange(i0[0], i1[0] + 1), np.arange(i0[1], i1[1] + 1),
                                     np.arange(i0[2], i1[2] + 1), indexing="ij")
            c = ((ix * dims[1] + iy) * dims[2] + iz).ravel()
            lists_c.append(c)
            lists_i.append(np.full(c.size, i, np.int64))
        if not lists_c:
            return np.zeros(ncell + 1, np.int64), np.zeros(0, np.int64)
        c = np.concatenate(lists_c)
        it = np.concatenate(lists_i)
        order = np.lexsort((it, c))
        c, it = c[order], it[order]
        counts = np.bincount(c, minlength=ncell)
        start = np.zeros(ncell + 1, np.int64)
        np.cumsum(counts, out=start[1:])
        return start, np.ascontiguousarray(it)

    v_start, v_items = csr(void_boxes)
    s_start, s_items = csr(solid_boxes)
    grid_f = np.array([bmin[0], bmin[1], bmin[2], cell], float)
    return grid_f, dims, v_start, v_items, s_start, s_items


def _prim_box(prim, typ, solid: bool):
    p = np.asarray(prim, float)
    if solid:
        if typ == 0:
            lo = np.minimum(p[0:3], p[3:6]) - p[6]
            hi = np.maximum(p[0:3], p[3:6]) + p[6]
        else:
            r = np.hypot(p[3], p[4])
            lo = p[0:3] - np.array([r, r, p[5]])
            hi = p[0:3] + np.array([r, r, p[5]])
        return lo, hi
    if typ == 0:
        R, hw = p[6], p[7]
        lo = np.minimum(p[0:3], p[3:6]) - np.array([R, R, 0.0])
        hi = np.maximum(p[0:3], p[3:6]) + np.array([R, R, hw + R])
        return lo, hi
    if typ == 1:
        return p[0:3] - p[3:6], p[0:3] + p[3:6]
    r = np.hypot(p[3], p[4])
    return p[0:3] - np.array([r, r, p[5]]), p[0:3] + np.array([r, r, p[5]])


def _assemble(void, vtype, solid, stype, waves, octaves, zones, cell, ob_max):
    void = np.ascontiguousarray(np.array(void, float).reshape(-1, 8))
    vtype = np.ascontiguousarray(np.array(vtype, np.int64))
    solid = np.ascontiguousarray(np.array(solid, float).reshape(-1, 8))
    stype = np.ascontiguousarray(np.array(stype, np.int64))
    vboxes = [_prim_box(void[i], vtype[i], False) for i in range(len(void))]
    sboxes = [_prim_box(solid[i], stype[i], True) for i in range(len(solid))]
    lo = np.min([b[0] for b in vboxes], axis=0) - ob_max
    hi = np.max([b[1] for b in vboxes], axis=0) + ob_max
    margin = K.GRID_MARGIN_M
    gmin = lo - margin
    gmax = hi + margin
    grid_f, dims, v_start, v_items, s_start, s_items = _build_grid(gmin, gmax, cell, vboxes, sboxes, margin)
    out = {
        "grid_f": grid_f, "grid_i": dims.astype(np.int64), "void_prims": void, "void_type": vtype,
        "v_start": v_start, "v_items": v_items, "solid_prims": solid, "solid_type": stype,
        "s_start": s_start, "s_items": s_items, "waves": waves, "octaves": octaves,
        "zones": np.ascontiguousarray(np.array(zones, float).reshape(-1, 5)),
        "bounds_min": lo, "bounds_max": hi,
        "noise_min": -float(np.sum(octaves[octaves[:, 3] == 1, 2])) - 1e-9,
    }
    out["ob_factor"], out["step_factor"], out["lipschitz"] = _lipschitz(out)
    return out


def _lipschitz(a, n: int = 4000, h: float = 1e-5):
    """Numerical Lipschitz estimates of the roughness (finite differences at seeded points).

    Returns the step factor of the overbreak bound ``1 / (1.02 + 1.5 L_ob)``, the
    full-field step factor ``min(0.45, 1 / (1.02 + 1.5 L_all))`` and the estimates; the
    1.5 safety factor covers the maximum not being sampled exactly. 1.02 bounds the
    smooth drift field (1/cos of the steepest ramp).
    """
    rng = np.random.default_rng(12345)
    lo, hi = a["bounds_min"], a["bounds_max"]
    P = rng.uniform(lo, hi, size=(n, 3))
    if a["zones"].shape[0]:
        zc = a["zones"][rng.integers(0, a["zones"].shape[0], n)]
        P = np.vstack([P, zc[:, :3] + rng.normal(0.0, 1.0, (n, 3)) * zc[:, 3:4]])
    P = np.ascontiguousarray(P)

    def parts(Q):
        ob = np.empty(Q.shape[0])
        tex = np.empty(Q.shape[0])
        K.noise_parts_many(np.ascontiguousarray(Q), a["waves"], a["octaves"], a["zones"], ob, tex)
        return ob, tex

    ob0, tx0 = parts(P)
    g_ob = np.zeros((P.shape[0], 3))
    g_all = np.zeros((P.shape[0], 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        ob1, tx1 = parts(P + e)
        g_ob[:, k] = (ob1 - ob0) / h
        g_all[:, k] = (ob1 + tx1 - ob0 - tx0) / h
    L_ob = float(np.linalg.norm(g_ob, axis=1).max())
    L_all = float(np.linalg.norm(g_all, axis=1).max())
    return 1.0 / (1.02 + 1.5 * L_ob), min(0.45, 1.0 / (1.02 + 1.5 * L_all)), {"overbreak": L_ob, "total": L_all}


def _smooth_field(a, P):
    """Smooth design field (no roughness, no structures) at points P."""
    P = np.ascontiguousarray(P, dtype=float)
    out = np.empty(P.shape[0])
    K.sdf_many(P, a["grid_f"], a["grid_i"], a["void_prims"], a["void_type"], a["v_start"], a["v_items"],
               a["solid_prims"], a["solid_type"], a["s_start"], a["s_items"], a["waves"], a["octaves"], a["zones"],
               np.eye(4), np.zeros((0, 8)), np.zeros(0, np.int64), np.zeros(4), False, False, out)
    return out


def _cast_arrays(a, O, D, max_range, step_factor, with_solids=True):
    out = np.empty(O.shape[0])
    ss = a["s_start"] if with_solids else np.zeros_like(a["s_start"])
    K.cast_rays(np.ascontiguousarray(O), np.ascontiguousarray(D), float(max_range), step_factor, MIN_STEP_M, 4000, 1e-4,
                a["grid_f"], a["grid_i"], a["void_prims"], a["void_type"], a["v_start"], a["v_items"],
                a["solid_prims"], a["solid_type"], ss, a["s_items"], a["waves"], a["octaves"], a["zones"],
                np.eye(4), np.zeros((0, 8)), np.zeros(0, np.int64), np.zeros(4), True, a["noise_min"], a["ob_factor"], out, np.empty(out.shape[0], np.int64))
    return out


class _Prims:
    """Growing primitive rows with their kernel type codes and the drift each belongs to."""

    def __init__(self):
        self.rows, self.types, self.owners = [], [], []

    def add(self, row, typ: int, owner: int) -> None:
        self.rows.append(row)
        self.types.append(typ)
        self.owners.append(owner)


def _world_params(preset: str, seed: int, params: WorldParams | None) -> tuple[WorldParams, int]:
    """The checked parameters (``params`` or the preset's) and the seed as an int."""
    if params is None:
        if preset not in PRESETS:
            raise InputError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
        params = PRESETS[preset]
    seed = int(seed)
    if seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed}")
    _check_params(params)
    return params, seed


def _level_offset(k: int, dz: float) -> np.ndarray:
    """Translation of level copy ``k`` (``dz`` below per level)."""
    return np.array([0.0, 0.0, -k * dz])


def _section_drifts(g: _Graph) -> tuple[int, int]:
    """The first level's longest main drift (irregular roof) and the second longest (regular, meshed)."""
    main0 = [k for k, e in enumerate(g.edges) if e[3] == "main" and e[4] == 0]
    main_len = [float(np.linalg.norm(np.diff(g.edges[k][2][:, :2], axis=0), axis=1).sum()) for k in main0]
    long_mains = [k for k, _L in sorted(zip(main0, main_len, strict=True), key=lambda z: -z[1])]
    irr = long_mains[0]
    reg = long_mains[1] if len(long_mains) > 1 else long_mains[0]
    return irr, reg


def _fall_outs(void: _Prims, poly, owner: int, H: float, rng: np.random.Generator):
    """Roof fall-outs (ellipsoid cavities) around the middle of ``poly``; returns the resampled
    points, their arc lengths and the middle index."""
    P, t, n, s = _resample(poly, 1.0)
    mid = len(P) // 2
    for j in range(max(0, mid - 8), min(len(P), mid + 8)):
        if rng.uniform() < 0.75:
            c = P[j] + np.array([*(n[j] * rng.uniform(-0.9, 0.9)), H - rng.uniform(0.2, 0.5)])
            void.add([c[0], c[1], c[2], rng.uniform(0.8, 1.6), rng.uniform(0.8, 1.6), rng.uniform(0.45, 0.9), 0, 0],
                     1, owner)
    return P, s, mid


def _sump_pit(void: _Prims, g: _Graph, feats: dict) -> dict:
    """The sump pit near the end of the Y branch, offset to one side of the centreline.

    Returns the pit's site: ``drift``, ``centre`` (pit centre), ``yaw``, ``floor`` (the branch
    point beside it) and ``side`` (+1: the pit lies left of the centreline).
    """
    sb = feats["sump"]["drift"]
    Pb, tb, nb, sbs = _resample(g.edges[sb][2], 0.5)
    j_pit = max(0, len(Pb) - 1 - int(5.0 / 0.5))
    side = 1.0
    pit_c = Pb[j_pit] + np.array([*(nb[j_pit] * side * 1.45), -0.65])
    yaw = math.atan2(tb[j_pit][1], tb[j_pit][0])
    void.add([pit_c[0], pit_c[1], pit_c[2], 1.8, 0.7, 0.85, yaw, 0.0], 2, sb)
    feats["sump"].update({"s_m": float(sbs[j_pit]), "centre": [float(x) for x in Pb[j_pit]]})
    return {"drift": sb, "centre": pit_c, "yaw": yaw, "floor": Pb[j_pit], "side": side}


def _repeat_voids(void: _Prims, zones: list, g: _Graph, rep: dict, irr: int, cavities: range, pit: dict,
                  H: float, dz: float, rng: np.random.Generator) -> None:
    """Rough zones, roof fall-outs and the sump pit of every level copy (``rep["copies"]``).

    An exact copy repeats the fall-outs ``cavities`` of level 0; a near copy draws them anew
    around the same place.
    """
    exact = rep["mode"] == "exact"
    # zones reach 3 r (kernel cut-off): keep them within one level so copies do not leak into each other
    rmax = (dz - H - 0.5) / 3.0
    for z in zones:
        z[3] = min(z[3], rmax)
    zones0 = [list(z) for z in zones]
    for k, cm in rep["copies"].items():
        o = _level_offset(k, dz)
        zones.extend([[*(np.array(z[:3]) + o), z[3], z[4]] for z in zones0])
        if exact:  # the same fall-outs
            for i in cavities:
                void.add([*(np.array(void.rows[i][:3]) + o), *void.rows[i][3:]], 1, cm[irr])
        else:  # near copy: fall-outs drawn anew around the same place
            _fall_outs(void, g.edges[cm[irr]][2], cm[irr], H, rng)
        void.add([*(pit["centre"] + o), 1.8, 0.7, 0.85, pit["yaw"], 0.0], 2, cm[pit["drift"]])


def _void_primitives(g: _Graph, feats: dict, params: WorldParams, rep: dict | None, rng: np.random.Generator):
    """Void primitives (drift segments, roof fall-outs, sump pit) and rough zones of the mine.

    Fills ``feats`` (``irregular_roof``, ``regular``, ``sump``); returns the voids, the rough
    zones, the regular (meshed) drift and the sump pit's site (see :func:`_sump_pit`).
    """
    R = params.width_m / 2.0
    hw = params.wall_height_m
    H = hw + R
    void = _Prims()
    for k, (_a, _b, poly, _kind, _lev) in enumerate(g.edges):
        for i in range(len(poly) - 1):
            void.add([*poly[i], *poly[i + 1], R, hw], 0, k)
    # section types on the first level's main drift: irregular roof, meshed, regular
    irr, reg = _section_drifts(g)
    zones = []
    cav0 = len(void.rows)
    P, s, mid = _fall_outs(void, g.edges[irr][2], irr, H, rng)
    cav1 = len(void.rows)
    zc = P[mid] + np.array([0, 0, H - 0.5])
    zones.append([*zc, 6.0, 0.9])
    feats["irregular_roof"] = {"drift": irr, "s_m": float(s[mid])}
    feats["regular"] = {"drift": reg, "s_m": float(np.linalg.norm(np.diff(g.edges[reg][2], axis=0), axis=1).sum() / 2)}
    # a second, milder rough zone somewhere else on the first level
    par0 = [k for k, e in enumerate(g.edges) if e[3] == "parallel" and e[4] == 0]
    if par0:
        Pp, _, _, _ = _resample(g.edges[par0[0]][2], 1.0)
        zones.append([*(Pp[len(Pp) // 2] + np.array([0, 0, 2.0])), 8.0, 0.5])
    pit = _sump_pit(void, g, feats)
    if rep is not None:
        _repeat_voids(void, zones, g, rep, irr, range(cav0, cav1), pit, H, float(params.level_spacing_m), rng)
    return void, zones, reg, pit


def _bolt_rays(g: _Graph, params: WorldParams, skip: set, mesh_edge: int, rng: np.random.Generator):
    """Rays from the drift axis at wall height to where the rock bolts go.

    Rings every ``bolt_spacing_m`` (none within 3 m of a junction or end, so bolts do not
    float in intersections), 5 bolts over the arch at seeded angles. Returns origins,
    directions, the drift of each ray and the ray indices of each ring of ``mesh_edge``.
    """
    hw = params.wall_height_m
    bolt_ok_kinds = ("main", "parallel", "ramp", "ring", "crosscut", "branch", "heading")
    Os, Ds, Downer = [], [], []
    strap_rings = []
    for k, (_a, _b, poly, kind, _lev) in enumerate(g.edges):
        if kind not in bolt_ok_kinds or k in skip:
            continue
        P, t, n, s = _resample(poly, params.bolt_spacing_m)
        # skip rings within 3 m of a junction/end so bolts do not float in intersections
        L = s[-1] + params.bolt_spacing_m / 2 if len(s) else 0
        keep = (s > 3.0) & (s < L - 3.0)
        for j in np.flatnonzero(keep):
            ring = []
            for ang in (-60.0, -30.0, 0.0, 30.0, 60.0):
                a = math.radians(ang + rng.uniform(-5, 5))
                d = np.array([*(n[j] * math.sin(a)), math.cos(a)])
                Os.append(P[j] + np.array([0, 0, hw]))
                Ds.append(d)
                Downer.append(k)
                ring.append(len(Os) - 1)
            if k == mesh_edge:
                strap_rings.append(ring)
    return Os, Ds, Downer, strap_rings


def _rock_bolts(solid: _Prims, g: _Graph, feats: dict, params: WorldParams, base: dict, skip: set, mesh_edge: int,
                rng: np.random.Generator) -> None:
    """Rock bolts placed on the rough surface of ``base`` and, on ``mesh_edge``, the steel straps
    ("mesh") linking the bolt heads of a ring; sets ``feats["meshed"]``."""
    Os, Ds, Downer, strap_rings = _bolt_rays(g, params, skip, mesh_edge, rng)
    if not Os:
        return
    O = np.array(Os)
    D = np.array(Ds)
    r = _cast_arrays(base, O, D, 6.0, params.trace_step_factor, with_solids=False)
    ok = np.isfinite(r)
    hit = O + D * np.where(ok, r, 0.0)[:, None]
    for i in np.flatnonzero(ok):
        a = hit[i] + D[i] * 0.03  # 3 cm inside the rock
        b = hit[i] - D[i] * 0.07  # plate + nut stand 7 cm proud
        solid.add([*a, *b, 0.06, 0.0], 0, Downer[i])
    for ring in strap_rings:  # "mesh": steel straps linking the bolt heads of a ring
        for u, v in zip(ring[:-1], ring[1:], strict=True):
            if ok[u] and ok[v]:
                a = hit[u] - D[u] * 0.05
                b = hit[v] - D[v] * 0.05
                solid.add([*a, *b, 0.025, 0.0], 0, mesh_edge)
    feats["meshed"] = {"drift": mesh_edge, "s_m": feats["regular"]["s_m"]}


def _services(solid: _Prims, g: _Graph, params: WorldParams, base: dict, skip: set) -> None:
    """Services along main drifts and ramps: pipe (left wall), two cables (right wall), duct under the roof."""
    R = params.width_m / 2.0
    H = params.wall_height_m + R
    for k, (_a, _b, poly, kind, _lev) in enumerate(g.edges):
        if kind not in ("main", "ramp") or k in skip:
            continue
        _, nseg, _ = _frames(poly)
        for lat, hgt, rad in ((R - 0.35, 1.9, 0.08), (-(R - 0.2), 2.55, 0.025), (-(R - 0.2), 2.7, 0.02)):
            Q = _offset_polyline(poly, lat, hgt)
            mids = 0.5 * (Q[:-1] + Q[1:])
            behind = mids + np.column_stack([nseg * math.copysign(0.8, lat), np.zeros(len(mids))])
            open_ = _smooth_field(base, behind) > 0.0  # no wall behind: a junction mouth, the service is routed over it
            for i in np.flatnonzero(~open_):
                solid.add([*Q[i], *Q[i + 1], rad, 0.0], 0, k)
        solid.rows.extend(_capsule_chain(_offset_polyline(poly, -0.9, H - 0.85), 0.4))
        solid.types.extend([0] * (len(poly) - 1))
        solid.owners.extend([k] * (len(poly) - 1))


def _railings(solid: _Prims, pit: dict) -> None:
    """Railings along the sump pit (posts every ~1.2 m, rails at 0.5 m and 1.05 m)."""
    c, yawp, side, sb = pit["centre"], pit["yaw"], pit["side"], pit["drift"]
    ca, sa = math.cos(yawp), math.sin(yawp)
    along = np.array([ca, sa, 0.0])
    across = np.array([-sa, ca, 0.0])
    floor_z = pit["floor"][2]  # the branch is flat: any of its points gives the floor height
    edge_c = np.array([c[0], c[1], floor_z]) - across * side * (0.7 + 0.12)
    posts = [edge_c + along * x for x in np.linspace(-1.8, 1.8, 4)]
    for q in posts:
        solid.add([q[0], q[1], floor_z - 0.05, q[0], q[1], floor_z + 1.05, 0.03, 0.0], 0, sb)
    for hgt in (0.5, 1.05):
        a = posts[0] + np.array([0, 0, hgt])
        b = posts[-1] + np.array([0, 0, hgt])
        solid.add([*a, *b, 0.025, 0.0], 0, sb)


def _repeat_solids(solid: _Prims, rep: dict, rail0: int, dz: float) -> None:
    """Copies on every level copy: every structure of the unit (exact) or the railings (rows
    from ``rail0`` on) only (near)."""
    exact = rep["mode"] == "exact"
    n0 = len(solid.rows)
    for k, cm in rep["copies"].items():
        o6 = np.array([*_level_offset(k, dz), *_level_offset(k, dz), 0.0, 0.0])
        for i in range(n0):
            if (exact and solid.owners[i] in cm) or (not exact and i >= rail0):
                solid.add(list(np.asarray(solid.rows[i], float) + o6), solid.types[i], cm[solid.owners[i]])


def _solid_primitives(g: _Graph, feats: dict, params: WorldParams, base: dict, rep: dict | None, reg: int,
                      pit: dict, rng: np.random.Generator) -> _Prims:
    """Solid structures: rock bolts and straps, services, sump railings and their level copies."""
    exact = rep is not None and rep["mode"] == "exact"
    # structures of an exact level copy are copied from level 0, not placed anew
    skip = {e for cm in rep["copies"].values() for e in cm.values()} if exact else set()
    solid = _Prims()
    _rock_bolts(solid, g, feats, params, base, skip, reg, rng)
    _services(solid, g, params, base, skip)
    rail0 = len(solid.rows)
    _railings(solid, pit)
    if rep is not None:
        _repeat_solids(solid, rep, rail0, float(params.level_spacing_m))
    return solid


def _curve_and_parking(g: _Graph, feats: dict, reg: int) -> list:
    """Marks the first ring/ramp drift as ``feats["curve"]`` and returns the vehicle's parking
    poses, left of the centreline in the regular section: [0] where it is parked during the
    survey, [1] moved 5 m back along the drift (also in ``feats["parking_sites"]``)."""
    ring_edges = [k for k, e in enumerate(g.edges) if e[3] in ("ring", "ramp")]
    ce = ring_edges[0]
    feats["curve"] = {"drift": ce, "s_m": float(np.linalg.norm(np.diff(g.edges[ce][2], axis=0), axis=1).sum() / 2)}
    parking = []
    for k, back_m in ((reg, 0.0), (reg, 5.0)):
        P, t, n, s = _resample(g.edges[k][2], 0.5)
        jj = max(0, len(P) // 2 - int(back_m / 0.5))
        T = np.eye(4)
        xa = np.array([t[jj][0], t[jj][1], 0.0])
        ya = np.array([n[jj][0], n[jj][1], 0.0])
        T[:3, 0], T[:3, 1], T[:3, 2] = xa, ya, [0, 0, 1]
        T[:3, 3] = P[jj] + ya * 1.15 + np.array([0, 0, 0.01])  # 0.15 m from the left wall
        parking.append(T)
        feats.setdefault("parking_sites", []).append({"drift": k, "s_m": float(s[jj])})
    return parking


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
