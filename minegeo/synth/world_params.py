"""Parameters of the synthetic mine (:class:`WorldParams`, the presets) and the wall-roughness model they set.

The roughness of the rock wall is a sum of seeded octaves of sine waves; :func:`roughness_amplitudes`
gives the amplitude of each octave for a lining (:data:`LININGS`) so that the wall's standard
deviation about its mean surface is the one asked for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from minegeo.errors import InputError


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
