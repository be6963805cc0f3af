"""Figures of the intersection knowledge base (docs/intersections.md): plan, descriptors, similarities.

Usage::

    python examples/intersections_figures.py [OUT_DIR]      # default docs/img

Builds the issue-18 synthetic network (three alike 4-way crossings X1-X3 with roofs at 3.0 / 3.6 /
4.2 m, a T and a Y with a 40 degree branch), its knowledge base, and writes

* ``intersections_plan.png``: the map's wall points, the drift skeleton and the invariant points;
* ``intersections_descriptors.png``: PWCV (polar) and CWC (bands x sectors) of X1, X2, T, Y and of
  the T with 25 % of its wall removed (like Liang et al. 2024, Fig. 15);
* ``intersections_similarity.png``: PWCV and CWC similarity matrices (like their Fig. 16).
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from minegeo.semantic import build_knowledge_base, drift_skeleton, pwcv, similarity, similarity_matrix  # noqa: E402
from minegeo.synth import intersections_network, junction_truth, network_cloud  # noqa: E402


def _names(kb, net):
    truth = junction_truth(net)
    names = [n for n in net.names if n]
    d = np.hypot(*(kb.invariant_points[:, None, :2] - truth[None]).transpose(2, 0, 1))
    return [names[int(np.argmin(d[i]))] for i in range(len(kb))], d.min(axis=1)


def _plan(P, sk, kb, names, out):
    fig, ax = plt.subplots(figsize=(11, 5.2))
    h = P[:, 2] - sk.floor.height(P[:, :2])
    W = P[(h > 0.4) & (h < 2.2)][::6]
    ax.scatter(W[:, 0], W[:, 1], s=0.2, c="0.55", rasterized=True, label="wall points (0.4-2.2 m)")
    ij = np.argwhere(sk.skeleton)
    S = sk.origin + (ij + 0.5) * sk.cell_m
    ax.scatter(S[:, 0], S[:, 1], s=0.3, c="tab:blue", rasterized=True, label="skeleton (Zhang-Suen)")
    C = kb.invariant_points
    ax.scatter(C[:, 0], C[:, 1], s=40, c="tab:red", marker="x", label="invariant points")
    for c, n, r in zip(C, names, kb.clearance_m, strict=True):
        ax.add_patch(plt.Circle(c[:2], r, fill=False, color="tab:red", lw=0.8))
        ax.add_patch(plt.Circle(c[:2], kb.params.descriptor.radius_m, fill=False, color="tab:orange", lw=0.6,
                                ls="--"))
        ax.annotate(n, c[:2] + (3.0, 3.0), color="tab:red")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, map frame)")
    ax.set_ylabel("y (m)")
    ax.set_title("Synthetic network: walls, skeleton, invariant points (largest empty circle, red) and "
                 "descriptor radius R = 12 m (orange)", fontsize=9)
    leg = ax.legend(loc="lower right", fontsize=8)
    for handle in leg.legend_handles:
        handle.set_sizes([20.0])
    fig.tight_layout()
    fig.savefig(out, dpi=130)
    plt.close(fig)


def _descriptors(kb, names, occluded_T, out):
    rows = [(n, kb.pwcv[i], kb.cwc[i]) for i, n in enumerate(names) if n in ("X1", "X2", "T", "Y")]
    rows.sort(key=lambda r: ["X1", "X2", "T", "Y"].index(r[0]))
    rows.append(("T, 25 % wall removed", occluded_T[0], occluded_T[1]))
    d = kb.params.descriptor
    theta = (np.arange(d.n_sectors) + 0.5) * 2 * np.pi / d.n_sectors
    fig = plt.figure(figsize=(13, 5.4))
    for k, (n, v, m) in enumerate(rows):
        ax = fig.add_subplot(2, len(rows), k + 1, projection="polar")
        rng = np.where(v > 0, (1.0 - v) * d.radius_m, np.nan)
        ax.plot(theta, rng, ".", ms=1.5, color="tab:blue")
        ax.set_ylim(0, d.radius_m)
        ax.set_title(f"{n}\nPWCV: wall range d_k (m)", fontsize=8)
        ax.tick_params(labelsize=6)
        ax2 = fig.add_subplot(2, len(rows), len(rows) + k + 1)
        ax2.imshow(m, origin="lower", aspect="auto", cmap="viridis", vmin=0, vmax=1,
                   extent=(0, 360, d.band_start_m, d.band_start_m + d.n_bands * d.band_m))
        ax2.set_title("CWC: closeness 1 - d/R", fontsize=8)
        ax2.set_xlabel("sector (deg)", fontsize=7)
        ax2.set_ylabel("height above floor (m)", fontsize=7)
        ax2.tick_params(labelsize=6)
    fig.tight_layout()
    fig.savefig(out, dpi=130)
    plt.close(fig)


def _similarity(kb, names, out):
    order = np.argsort([["X1", "X2", "X3", "T", "Y"].index(n) for n in names])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.4))
    for ax, kind in zip(axes, ("pwcv", "cwc"), strict=True):
        S = similarity_matrix(kb, kind)[np.ix_(order, order)]
        im = ax.imshow(S, vmin=0, vmax=1, cmap="magma")
        for i in range(len(S)):
            for j in range(len(S)):
                ax.text(j, i, f"{S[i, j]:.2f}", ha="center", va="center", fontsize=8,
                        color="black" if S[i, j] > 0.6 else "white")
        lab = [names[i] for i in order]
        ax.set_xticks(range(len(S)), lab)
        ax.set_yticks(range(len(S)), lab)
        ax.set_title(f"{kind.upper()} similarity (max over shifts; threshold 0.8)", fontsize=9)
    fig.colorbar(im, ax=axes, shrink=0.8)
    fig.savefig(out, dpi=130)
    plt.close(fig)


def main(out_dir: Path) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    net = intersections_network()
    P = network_cloud(net, seed=1).points
    kb = build_knowledge_base(P)
    sk = drift_skeleton(P, kb.params.skeleton)
    names, err = _names(kb, net)
    iT = names.index("T")
    C = kb.invariant_points[iT]
    Q = kb.cloud(iT)
    dxy = Q[:, :2] - C[:2]
    th = np.mod(np.arctan2(dxy[:, 1], dxy[:, 0]) - 1.3, 2 * np.pi)
    h = Q[:, 2] - C[2]
    r = np.hypot(dxy[:, 0], dxy[:, 1])
    wall = (h > 0.4) & (h < 2.2) & (r < 12) & (r > 1)
    width = np.sort(th[wall])[int(0.25 * wall.sum())]
    Qo = Q[~((th <= width) & (r > 1.0))]
    from minegeo.semantic import cwc

    occl = (pwcv(Qo, C), cwc(Qo, C))
    _plan(P, sk, kb, names, out_dir / "intersections_plan.png")
    _descriptors(kb, names, occl, out_dir / "intersections_descriptors.png")
    _similarity(kb, names, out_dir / "intersections_similarity.png")
    s_occ = similarity(occl[0], kb.pwcv[iT]).score
    print(f"intersections: {len(kb)} found, max invariant-point error {err.max():.3f} m; "
          f"occluded T vs T PWCV similarity {s_occ:.3f}; figures in {out_dir}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "docs" / "img")
