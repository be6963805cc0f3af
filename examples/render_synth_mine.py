"""Render the synthetic mine: a plan view and a close-up (docs/img/synth_plan.png, synth_closeup.png).

Usage::

    python examples/render_synth_mine.py [--seed 1] [--out docs/img]

The plan view shows the survey map (coloured by height) of the ``small`` preset with the
drift centrelines, the T/X/Y intersections, the ring roadway (loop), the ramp and the
ground control points. The close-up shows drift cross-sections from a profile scanner (a
Horizontal2D sensor turned into the cross-section plane) against the design horseshoe:
(a) a regular section with overbreak, bolts, straps, pipe, cables and duct, (b) the same
drift through the parked vehicle, (c) the irregular-roof section seen from the side in a
static ZEB-REVO-like scan, (d) the sump pit and its railings.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from minegeo.synth import (  # noqa: E402
    Horizontal2D,
    ZebRevo,
    build_map,
    build_world,
    make_gcps,
    simulate_scan,
    simulate_scan_2d,
)
from minegeo.synth.trajectory import _arc_lengths  # noqa: E402


def _pose_on(world, drift: int, s_m: float, height_m: float = 1.6) -> np.ndarray:
    P = world.drifts[drift].centreline
    S = _arc_lengths(P)
    q = np.array([np.interp(s_m, S, P[:, i]) for i in range(3)])
    k = int(np.clip(np.searchsorted(S, s_m, side="right") - 1, 0, len(P) - 2))
    t = P[k + 1] - P[k]
    t[2] = 0.0
    t /= np.linalg.norm(t)
    T = np.eye(4)
    T[:3, 0] = t
    T[:3, 1] = [-t[1], t[0], 0.0]
    T[:3, 2] = [0.0, 0.0, 1.0]
    T[:3, 3] = q + [0.0, 0.0, height_m]
    return T


def plan_view(world, cloud, gcps, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(11, 7.5))
    P = cloud.points
    order = np.argsort(P[:, 2])
    sc = ax.scatter(P[order, 0], P[order, 1], c=P[order, 2], s=0.15, cmap="viridis", linewidths=0, rasterized=True)
    for d in world.drifts:
        c = d.centreline
        style = {"ramp": ("r-", 1.2), "ring": ("m-", 1.2)}.get(d.kind, ("k-", 0.5))
        ax.plot(c[:, 0], c[:, 1], style[0], lw=style[1], alpha=0.8)
    colors = {"T": "tab:orange", "X": "tab:red", "Y": "tab:blue"}
    for it in world.intersections:
        ax.plot(it.position[0], it.position[1], "o", ms=9, mfc="none", mec=colors[it.type], mew=2)
        ax.annotate(it.type, it.position[:2], xytext=(6, 6), textcoords="offset points", fontsize=10,
                    color=colors[it.type], weight="bold")
    for i in world.dead_ends:
        ax.plot(world.nodes[i, 0], world.nodes[i, 1], "kx", ms=7)
    ax.plot(gcps.local_xyz[:, 0], gcps.local_xyz[:, 1], "^", color="crimson", ms=7, label="GCP on wall")
    ramp = next(d for d in world.drifts if d.kind == "ramp")
    mid = ramp.centreline[len(ramp.centreline) // 2]
    ax.annotate(f"ramp {world.features['ramp_slopes_deg'][0]:.1f} deg down", mid[:2], xytext=(10, -25),
                textcoords="offset points", color="r", fontsize=10, arrowprops={"arrowstyle": "->", "color": "r"})
    ring = next(d for d in world.drifts if d.kind == "ring")
    rm = ring.centreline[len(ring.centreline) // 2]
    ax.annotate("ring roadway (loop)", rm[:2], xytext=(-40, 25), textcoords="offset points", color="m",
                fontsize=10, arrowprops={"arrowstyle": "->", "color": "m"})
    sump = world.features["sump"]["centre"]
    ax.annotate("sump + railings", sump[:2], xytext=(15, 15), textcoords="offset points", fontsize=9,
                arrowprops={"arrowstyle": "->"})
    ax.plot([], [], "kx", label="dead end")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, map frame)")
    ax.set_ylabel("y (m, map frame)")
    s = world.summary()
    ax.set_title(f"minegeo.synth preset '{world.preset}', seed {world.seed}: {s['n_drifts']} drifts, "
                 f"{s['total_length_m']:.0f} m, {s['n_levels']} levels, {s['n_loops']} loops, "
                 f"survey map {len(cloud):,} points")
    fig.colorbar(sc, ax=ax, shrink=0.7, label="z (m)")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _profile(world, T_floor: np.ndarray, height_m: float = 1.6, step_deg: float = 0.1, seed: int = 0):
    """A cross-section profile: a Horizontal2D scanner whose scan plane is the drift cross-section.

    Returns (across, up) coordinates (m) relative to the floor centreline point of ``T_floor``.
    """
    n = T_floor[:3, 1]
    T = np.eye(4)
    T[:3, 0] = [0.0, 0.0, 1.0]  # scanner x: up
    T[:3, 1] = n  # scanner y: left
    T[:3, 2] = np.cross(T[:3, 0], T[:3, 1])
    T[:3, 3] = T_floor[:3, 3] + [0.0, 0.0, height_m]
    scan = simulate_scan_2d(world, Horizontal2D(angular_step_deg=step_deg), T, seed=seed)
    xy = scan.points()
    P = xy[:, :1] * T[:3, 0] + xy[:, 1:2] * T[:3, 1] + T[:3, 3]
    loc = P - T_floor[:3, 3]
    return loc @ n, loc[:, 2]


def _design(ax, world):
    R, hw = world.params.width_m / 2, world.params.wall_height_m
    a = np.linspace(0, np.pi, 100)
    prof = np.vstack([[[R, 0], [R, hw]], np.column_stack([R * np.cos(a), hw + R * np.sin(a)]),
                      [[-R, hw], [-R, 0], [R, 0]]])
    ax.plot(prof[:, 0], prof[:, 1], "r-", lw=0.8, label="design horseshoe 4.5 x 4.5 m")


def closeup(world, path: Path) -> None:
    fig, axs = plt.subplots(1, 4, figsize=(18, 5.0), gridspec_kw={"width_ratios": [1, 1, 2.2, 1.2]})
    # (a) cross-sections in the regular section: rough walls, bolts + straps, pipe, cables, duct, vehicle
    ax = axs[0]
    f = world.features["regular"]
    s_ring = 0.75 + 1.5 * round((f["s_m"] + 5.5 - 0.75) / 1.5)  # through a ring of rock bolts
    T = _pose_on(world, f["drift"], s_ring, 0.0)
    u, v = _profile(world, T, seed=1)
    ax.plot(u, v, ".", ms=1.0, color="0.2", label="profile, 0.1 deg")
    _design(ax, world)
    ax.set_title("(a) regular section: overbreak, bolts,\nstraps, pipe, cables, duct", fontsize=10)
    ax = axs[1]
    T = _pose_on(world, f["drift"], f["s_m"], 0.0)
    u, v = _profile(world, T, height_m=2.8, seed=2)
    ax.plot(u, v, ".", ms=1.0, color="tab:blue", label="profile through vehicle")
    _design(ax, world)
    ax.set_title("(b) same drift through the parked\nvehicle (a movable dynamic object)", fontsize=10)
    for ax in axs[:2]:
        ax.set_aspect("equal")
        ax.set_xlim(-3.2, 3.2)
        ax.set_ylim(-0.4, 5.2)
        ax.set_xlabel("across drift (m, left +)")
        ax.set_ylabel("above floor (m)")
        ax.legend(loc="lower center", fontsize=7, markerscale=6)
    # (c) dense static ZEB scan in the irregular-roof section, side view (centre slice)
    ax = axs[2]
    f = world.features["irregular_roof"]
    T = _pose_on(world, f["drift"], f["s_m"], 1.4)
    sc = simulate_scan(world, ZebRevo(angular_step_deg=0.125), T, seed=5)
    P = sc.points
    keep = (np.abs(P[:, 0]) < 10) & (np.abs(P[:, 1]) < 0.4)
    ax.scatter(P[keep, 0], P[keep, 2] + 1.4, s=0.3, c="0.2", linewidths=0, rasterized=True)
    ax.plot([-10, 10], [4.5, 4.5], "r--", lw=0.8, label="design crown 4.5 m")
    ax.plot([-10, 10], [0, 0], "r-", lw=0.8, label="design floor")
    ax.set_aspect("equal")
    ax.set_ylim(-0.8, 6.2)
    ax.set_xlabel("along drift (m)")
    ax.set_ylabel("above floor (m)")
    ax.set_title("(c) irregular roof (fall-outs): centre slice of a static ZEB-REVO-like scan", fontsize=10)
    ax.legend(loc="lower right", fontsize=7)
    # (d) cross-section through the sump pit and its railings
    ax = axs[3]
    s = world.features["sump"]
    T = _pose_on(world, s["drift"], s["s_m"], 0.0)
    u, v = _profile(world, T, height_m=2.0, step_deg=0.05, seed=3)
    ax.plot(u, v, ".", ms=1.2, color="0.2", label="profile")
    _design(ax, world)
    ax.set_aspect("equal")
    ax.set_xlim(-3.2, 3.2)
    ax.set_ylim(-2.0, 5.2)
    ax.set_xlabel("across drift (m, left +)")
    ax.set_ylabel("above floor (m)")
    ax.set_title("(d) sump pit (1.5 m deep) with\nrailings (rails at 0.5 and 1.05 m)", fontsize=10)
    ax.legend(loc="upper right", fontsize=7, markerscale=6)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "img"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    world = build_world("small", args.seed)
    cloud = build_map(world, seed=args.seed, spacing_m=3.0)
    gcps, _ = make_gcps(world, n=10, seed=args.seed)
    plan_view(world, cloud, gcps, out / "synth_plan.png")
    closeup(world, out / "synth_closeup.png")
    print(f"wrote {out / 'synth_plan.png'} and {out / 'synth_closeup.png'}")


if __name__ == "__main__":
    main()
