"""The figure of one poseidyn run (the family's ``plot``; matplotlib is imported when it draws,
never by :mod:`rvdjax.families.poseidyn`, which the jitted kernel uses)."""

from __future__ import annotations

import numpy as np

from rvdjax.families.poseidyn import plane_angle


def plot(path, scenario, params, infos, title: str | None = None):
    """Draw a POSEIDYN LQ-MPC run (paper 001): path, keep-out circle, rotating hyperplane
    snapshots, entry cone, thrust and distance to the docking point."""
    from rvdjax.plots import pyplot, save_figure

    plt = pyplot()

    active = np.asarray(infos.active)
    n = min(int(active.sum()) + 1, len(active))
    x = np.asarray(infos.x)[:n]
    u = np.asarray(infos.u)[: n - 1]
    t = np.concatenate([[0.0], np.cumsum(np.asarray(infos.dt)[: n - 1])])
    dock, obs = np.asarray(params.dock), np.asarray(params.obstacle)
    r_obs = float(params.r_obs)
    fig = plt.figure(figsize=(13, 6))
    ax = fig.add_subplot(1, 2, 1)
    ax.add_patch(plt.Circle(obs, r_obs, color="tab:blue", alpha=0.3, label="keep-out zone"))

    phis = np.asarray(plane_angle(params, np.asarray(infos.t)[:n]))
    for k, s in enumerate(np.linspace(0, n - 1, 6).astype(int)):
        e = np.array([np.cos(phis[s]), np.sin(phis[s])])
        p0 = obs + r_obs * e
        tangent = np.array([-e[1], e[0]])
        seg = np.stack([p0 - 0.6 * tangent, p0 + 0.6 * tangent])
        ax.plot(seg[:, 0], seg[:, 1], color="tab:blue", alpha=0.2 + 0.7 * k / 5, lw=1)
    a, h = float(params.cone_axis), float(params.half_angle)
    for sgn in (-1, 1):
        ray = dock + float(params.cone_range) * np.array([np.cos(a + sgn * h), np.sin(a + sgn * h)])
        ax.plot([dock[0], ray[0]], [dock[1], ray[1]], color="tab:green")
    ax.plot(x[:, 0], x[:, 1], "-o", ms=2, color="tab:red", label="chaser (truth)")
    ax.plot(*dock, "ks", label="docking point")
    ax.plot([], [], color="tab:blue", label="rotating hyperplane (snapshots)")
    ax.plot([], [], color="tab:green", label="entry cone")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title or f"{scenario.name}: closed loop")
    ax_u = fig.add_subplot(2, 2, 2)
    ax_u.step(t[: len(u)], u[:, 0], where="post", label="Fx [N]")
    ax_u.step(t[: len(u)], u[:, 1], where="post", ls="--", label="Fy [N]")
    ax_u.grid(alpha=0.3)
    ax_u.legend(fontsize=8)
    ax_r = fig.add_subplot(2, 2, 4)
    ax_r.plot(t, np.linalg.norm(x[:, :2] - dock, axis=1), label="distance to docking point [m]")
    ax_r.set_xlabel("time [s]")
    ax_r.grid(alpha=0.3)
    ax_r.legend(fontsize=8)
    save_figure(fig, path)
