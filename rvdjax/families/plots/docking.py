"""The figure of one docking run (the family's ``plot``; matplotlib is imported when it draws,
never by :mod:`rvdjax.families.docking`, which the jitted kernel uses)."""

from __future__ import annotations

import numpy as np


def plot(path, scenario, params, infos, title: str | None = None):
    """Draw a planar docking run: path, target keep-out and holding circles and port axis
    (snapshots, the target may translate), moving obstacles, thrust and torque, holding
    radius and phase / cone activity."""
    from rvdjax.plots import pyplot, save_figure

    plt = pyplot()

    active = np.asarray(infos.active)
    n = min(int(active.sum()) + 1, len(active))
    x = np.asarray(infos.x)[:n]
    u = np.asarray(infos.u)[: n - 1]
    r_hold = np.asarray(infos.guidance.r_hold)[:n]
    ts = float(params.ts)
    t = np.arange(n) * ts
    c0, v_t = np.asarray(params.target)[:2], np.asarray(params.target_vel)
    phi0, rate = float(params.target[2]), float(params.target_rate)
    r_t, r_port = float(params.r_t), float(params.r_port)
    centres = c0[None] + t[:, None] * v_t[None]
    obstacles = np.asarray(params.obstacles)
    radii = np.asarray(params.obstacle_radii)
    obs_on = np.asarray(params.obstacle_mask) > 0

    fig = plt.figure(figsize=(13, 6))
    ax = fig.add_subplot(1, 2, 1)
    snaps = np.linspace(0, n - 1, 6).astype(int)
    for k, s in enumerate(snaps):
        alpha = 0.15 + 0.7 * k / (len(snaps) - 1)
        c = centres[s]
        phi = phi0 + rate * s * ts
        e = np.array([np.cos(phi), np.sin(phi)])
        ax.add_patch(plt.Circle(c, r_t, color="k", alpha=0.25 * alpha))
        ax.add_patch(plt.Circle(c, r_hold[s], color="gray", fill=False, ls="--", alpha=alpha))
        ax.plot(
            *np.stack([c + r_port * e, c + (r_hold[s] + 0.15) * e]).T,
            color="tab:green",
            alpha=alpha,
        )
        ax.plot(*x[s, :2], "o", color="tab:red", alpha=alpha, ms=4)
        for j in np.flatnonzero(obs_on):
            o = obstacles[j, :2] + s * ts * obstacles[j, 2:]
            ax.add_patch(plt.Circle(o, radii[j], color="tab:blue", fill=False, alpha=alpha))
    phi = phi0 + rate * (n - 1) * ts
    h = float(params.half_angle)
    dock = centres[-1] + r_port * np.array([np.cos(phi), np.sin(phi)])
    for sgn in (-1, 1):
        ray = dock + 0.6 * np.array([np.cos(phi + sgn * h), np.sin(phi + sgn * h)])
        ax.plot(*np.stack([dock, ray]).T, color="tab:green", ls=":")
    ax.plot(x[:, 0], x[:, 1], "-", color="tab:red", label="chaser (truth)")
    ax.plot(centres[:, 0], centres[:, 1], "k:", lw=1, label="target centre")
    ax.plot([], [], color="gray", ls="--", label="holding radius (snapshots, later = darker)")
    ax.plot([], [], color="tab:green", label="port axis; final entry cone (dotted)")
    if obs_on.any():
        ax.plot([], [], color="tab:blue", label="obstacle keep-out zones")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title or f"{scenario.name}: closed loop")

    ax_u = fig.add_subplot(2, 2, 2)
    ax_u.step(t[: len(u)], u[:, 0], where="post", label="Fx [N]")
    ax_u.step(t[: len(u)], u[:, 1], where="post", ls="--", label="Fy [N]")
    ax_u.step(t[: len(u)], 10 * u[:, 2], where="post", ls=":", label="10 x torque [N m]")
    ax_u.grid(alpha=0.3)
    ax_u.legend(fontsize=8, ncol=3)
    ax_r = fig.add_subplot(2, 2, 4)
    ax_r.plot(t, r_hold, label="r_hold [m]")
    ax_r.plot(t, np.linalg.norm(x[:, :2] - centres, axis=1), label="distance to target [m]")
    ax_r.step(
        t,
        np.asarray(infos.guidance.cone_on)[:n].astype(float),
        where="post",
        label="entry cone active",
    )
    ax_r.axhline(r_t, color="k", lw=0.8, ls="--")
    ax_r.set_xlabel("time [s]")
    ax_r.grid(alpha=0.3)
    ax_r.legend(fontsize=8)
    save_figure(fig, path)
