"""Plots: planned trajectories with keep-out zones, and thrust histories (matplotlib, Agg)."""

from __future__ import annotations

import numpy as np


def plot_plan(path, ocp, solutions: dict, obstacles: dict | None = None, clarabel_x=None):
    """Draw one MPC plan: radial/along-track path with keep-out zones, and the thrust.

    Args:
        path: output file (png, pdf, svg).
        ocp: the problem (its x0 and horizon).
        solutions: label -> :class:`rvdjax.solver.Solution` (unbatched).
        obstacles: the scenario dict with "obstacles" (initial states), "radii" and "ts"
            (as :data:`rvdjax.problems.FASTMPC3D`); None for no obstacles.
        clarabel_x: (N, nx) Clarabel's planned states, drawn dashed for comparison.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax_u) = plt.subplots(1, 2, figsize=(12, 5.5), gridspec_kw={"width_ratios": [1.1, 1]})
    x0 = np.asarray(ocp.x0)
    N = ocp.N
    colors = ["tab:red", "tab:orange", "tab:purple", "tab:brown"]
    for (label, sol), c in zip(solutions.items(), colors, strict=False):
        x = np.vstack([x0, np.asarray(sol.x)])
        ax.plot(x[:, 1], x[:, 0], "-o", ms=2.5, color=c, label=label)
    if clarabel_x is not None:
        x = np.vstack([x0, np.asarray(clarabel_x)])
        ax.plot(x[:, 1], x[:, 0], "k--", lw=1, label="Clarabel (optimum)")
    if obstacles is not None:
        from rvdjax.problems import obstacle_centres

        ts = obstacles["ts"]
        centres = np.asarray(obstacle_centres(np.asarray(obstacles["obstacles"]), N, ts))
        for j, radius in enumerate(obstacles["radii"]):
            for t in range(0, N, 5):
                alpha = 0.15 + 0.6 * t / N
                circ = plt.Circle(
                    (centres[t, j, 1], centres[t, j, 0]),
                    radius,
                    color="tab:blue",
                    alpha=alpha,
                    fill=False,
                    lw=1,
                )
                ax.add_patch(circ)
            ax.plot(centres[:, j, 1], centres[:, j, 0], ":", color="tab:blue", lw=1)
        ax.plot([], [], color="tab:blue", label="keep-out zones (every 5th stage)")
    ax.plot([0], [0], "ks", label="target")
    ax.set_xlabel("along-track y [m]")
    ax.set_ylabel("radial x [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title("planned path (LVLH, radial vs along-track)")

    ts = obstacles["ts"] if obstacles is not None else 1.0
    for (label, sol), c in zip(solutions.items(), colors, strict=False):
        u = np.asarray(sol.u)
        t = np.arange(N) * ts
        for i, ls in zip(range(u.shape[1]), ["-", "--", ":"], strict=False):
            ax_u.step(
                t,
                u[:, i],
                where="post",
                color=c,
                ls=ls,
                label=f"{label} u{'xyz'[i] if u.shape[1] == 3 else i}",
            )
    ax_u.set_xlabel("time into the horizon [s]")
    ax_u.set_ylabel("thrust [N]")
    ax_u.grid(alpha=0.3)
    ax_u.legend(fontsize=7, ncol=2)
    ax_u.set_title("planned thrust")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
