"""Shared drawing pieces (matplotlib, Agg): planned trajectories of one QP, LVLH axes, cone
edges, the valve-firing timeline of a run with thrusters. Each guidance family draws its own
run's figure (its ``plot``) from these; this module imports no family."""

from __future__ import annotations

import numpy as np


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, no display needed), unless a
    backend was chosen already: ``MPLBACKEND`` (a Jupyter kernel sets it to its inline
    backend) or pyplot imported by the caller. Forcing Agg there would switch a notebook's
    inline backend off, and its later figures would not show."""
    import os
    import sys

    import matplotlib

    if "matplotlib.pyplot" not in sys.modules and not os.environ.get("MPLBACKEND"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int = 120) -> None:
    """Lay out, write and close a figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


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
    plt = pyplot()

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
        ts = obstacles["ts"]
        o = np.asarray(obstacles["obstacles"])
        times = ts * np.arange(1, N + 1)
        centres = o[None, :, :3] + times[:, None, None] * o[None, :, 3:]
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
    save_figure(fig, path)


def finish_lvlh_axes(ax, title):
    """Target marker, LVLH labels (radial up, along-track across), equal aspect, legend."""
    ax.plot([0], [0], "ks", label="target")
    ax.set_xlabel("along-track y [m]")
    ax.set_ylabel("radial x [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)


def cone_edges(apex, axis, half_angle, length):
    """Plot coordinates (along-track, radial) of a planar cone's two edges from ``apex``
    along the x-y LVLH direction ``axis`` (unit (2,) in x, y)."""
    edges = []
    for sgn in (1.0, -1.0):
        c, s_ = np.cos(sgn * half_angle), np.sin(sgn * half_angle)
        d = np.array([c * axis[0] - s_ * axis[1], s_ * axis[0] + c * axis[1]])
        end = apex + length * d
        edges.append(([apex[1], end[1]], [apex[0], end[0]]))
    return edges


def firing_timeline(path, scenario, infos, title: str | None = None):
    """The valve pulses of a run with thrusters: one row of on-bars per thruster over time.

    Args:
        infos: the run's StepInfo (leading step axis) with ``pulses`` (steps, T, P) [s].
    """
    plt = pyplot()

    t = np.asarray(infos.t)
    active = np.asarray(infos.active)
    start = np.asarray(infos.pulses.start)[active]
    width = np.asarray(infos.pulses.width)[active]
    t = t[active]
    T = start.shape[1]
    fig, ax = plt.subplots(figsize=(9, 0.45 * T + 1.4))
    for i in range(T):
        on = width[:, i, :] > 0
        bars = [
            (t[k] + start[k, i, p], width[k, i, p]) for k, p in zip(*np.nonzero(on), strict=True)
        ]
        ax.broken_barh(bars, (i - 0.35, 0.7), color="C0")
    labels = []
    for i, (d, r) in enumerate(
        zip(scenario.thrusters.direction, scenario.thrusters.position_m, strict=True)
    ):
        k = int(np.argmax(np.abs(d)))
        lever = np.cross(r, d)[2]
        arm = "" if abs(lever) < 1e-9 else (" ccw" if lever > 0 else " cw")
        labels.append(f"{i}: {'+-'[int(d[k] < 0)]}{'xyz'[k]}{arm}")
    ax.set_yticks(range(T), labels)
    ax.set_ylim(T - 0.5, -0.5)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("thruster")
    tset = scenario.thrusters
    ax.set_title(title or f"{scenario.name}: valve pulses ({tset.name}, {tset.modulator})")
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
