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
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _finish_lvlh_axes(ax, title):
    """Target marker, LVLH labels (radial up, along-track across), equal aspect, legend."""
    ax.plot([0], [0], "ks", label="target")
    ax.set_xlabel("along-track y [m]")
    ax.set_ylabel("radial x [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)


def plot_rendezvous(path, scenario, params, infos, title: str | None = None):
    """Draw one rendezvous run: path with keep-out snapshots, thrust, range and margins.

    Args:
        path: output file.
        scenario: the :class:`rvdjax.scenarios.Scenario` (for the title).
        params: its :class:`rvdjax.families.rendezvous.Params`.
        infos: the run's :class:`rvdjax.loop.StepInfo` (leading axis: step).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    active = np.asarray(infos.active)
    n = int(active.sum()) + 1  # include the state after the last active step
    x = np.asarray(infos.x)[: min(n, len(active))]
    u = np.asarray(infos.u)[: n - 1]
    ts = float(params.ts)
    t = np.arange(len(x)) * ts
    obstacles = np.asarray(params.obstacles)
    radii = np.asarray(params.radii)
    mask = np.asarray(params.obstacle_mask) > 0
    d = obstacles.shape[1] // 2

    fig = plt.figure(figsize=(13, 6))
    ax = fig.add_subplot(1, 2, 1)
    ax.plot(x[:, 1], x[:, 0], "-", color="tab:red", lw=1.5, label="chaser (truth)")
    ax.plot(x[0, 1], x[0, 0], "o", color="tab:red")
    snaps = np.linspace(0, len(x) - 1, 6).astype(int)
    for j in np.flatnonzero(mask):
        path_o = obstacles[j, :d][None] + t[:, None] * obstacles[j, d:][None]
        ax.plot(path_o[:, 1], path_o[:, 0], ":", color="tab:blue", lw=1)
        for k, s in enumerate(snaps):
            alpha = 0.15 + 0.7 * k / max(len(snaps) - 1, 1)
            ax.add_patch(
                plt.Circle(
                    (path_o[s, 1], path_o[s, 0]),
                    radii[j],
                    color="tab:blue",
                    fill=False,
                    alpha=alpha,
                )
            )
            ax.plot(x[s, 1], x[s, 0], ".", color="tab:red", alpha=alpha)
    if mask.any():
        ax.plot([], [], color="tab:blue", label="keep-out zones (snapshots, later = darker)")
    _finish_lvlh_axes(ax, title or f"{scenario.name}: closed loop")

    ax_u = fig.add_subplot(2, 2, 2)
    for i, ls in zip(range(u.shape[1]), ["-", "--", ":"], strict=False):
        ax_u.step(t[: len(u)], u[:, i], where="post", ls=ls, label=f"u{'xyz'[i]}")
    ax_u.set_ylabel("thrust [N]")
    ax_u.grid(alpha=0.3)
    ax_u.legend(fontsize=8, ncol=3)

    ax_r = fig.add_subplot(2, 2, 4)
    ax_r.semilogy(t, np.linalg.norm(x[:, :d], axis=1), color="k", label="range to target")
    margins = np.asarray(infos.margins["keep_out"])[: len(x)]
    for j in np.flatnonzero(mask):
        ax_r.semilogy(
            t, np.maximum(margins[:, j], 1e-3), label=f"keep-out margin {j + 1} (floored at 1 mm)"
        )
    ax_r.axhline(float(params.stop_radius), color="gray", ls="--", lw=1, label="holding distance")
    ax_r.set_xlabel("time [s]")
    ax_r.set_ylabel("[m]")
    ax_r.grid(alpha=0.3, which="both")
    ax_r.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_docking(path, scenario, params, infos, title: str | None = None):
    """Draw a planar docking run: path, target keep-out and holding circles and port axis
    (snapshots, the target may translate), moving obstacles, thrust and torque, holding
    radius and phase / cone activity."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_poseidyn(path, scenario, params, infos, title: str | None = None):
    """Draw a POSEIDYN LQ-MPC run (paper 001): path, keep-out circle, rotating hyperplane
    snapshots, entry cone, thrust and distance to the docking point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    from rvdjax.families.poseidyn import plane_angle

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
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _cone_edges(apex, axis, half_angle, length):
    """Plot coordinates (along-track, radial) of a planar cone's two edges from ``apex``
    along the x-y LVLH direction ``axis`` (unit (2,) in x, y)."""
    edges = []
    for sgn in (1.0, -1.0):
        c, s_ = np.cos(sgn * half_angle), np.sin(sgn * half_angle)
        d = np.array([c * axis[0] - s_ * axis[1], s_ * axis[0] + c * axis[1]])
        end = apex + length * d
        edges.append(([apex[1], end[1]], [apex[0], end[0]]))
    return edges


def plot_phases(path, scenario, params, infos, title: str | None = None):
    """Draw a three-phase thesis run (paper 003): the radial / along-track path coloured by
    phase with the keep-out sphere r1 and the approach cone; a zoom on the approach and
    docking (overshoot line at r2, docking cone at the port, at the final attitude of the
    target); distance to the port (log) and delta-v per step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    active = np.asarray(infos.active)
    n = min(int(active.sum()) + 1, len(active))
    x = np.asarray(infos.x)[:n]
    u = np.asarray(infos.u)[:n]
    t = np.asarray(infos.t)[:n]
    phase = np.asarray(infos.phase)[:n]
    colors = ["tab:red", "tab:orange", "tab:green"]
    names = ["rendezvous", "approach", "docking"]
    r1, r2 = float(params.r1), float(params.r2)
    ang = float(params.target_angle0) + float(params.target_rate) * t[-1]
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    axis = rot @ np.asarray(params.axis_body)[:2]
    port = rot @ np.asarray(params.port_body)[:2]
    half = np.asarray(params.half_angle)

    fig = plt.figure(figsize=(17, 6))
    grid = fig.add_gridspec(2, 3, width_ratios=[1.25, 1.0, 1.1])
    ax = fig.add_subplot(grid[:, 0])
    ax_z = fig.add_subplot(grid[:, 1])
    for a_, zoom in ((ax, False), (ax_z, True)):
        for k in range(3):
            sel = phase == k
            if sel.any():
                a_.plot(x[sel, 1], x[sel, 0], ".-", ms=3, color=colors[k], label=names[k])
        circle = plt.Circle((0.0, 0.0), r1, fill=False, ls="--", color="0.4")
        a_.add_patch(circle)
        reach = (1.6 if zoom else 3.0) * r1
        for i, (ex, ey) in enumerate(_cone_edges(np.zeros(2), axis, half[0], reach)):
            a_.plot(ex, ey, ":", color="tab:purple", label="approach cone" if i == 0 else None)
        if zoom:
            normal = np.array([-axis[1], axis[0]])
            p_os = r2 * axis
            a_.plot(
                [p_os[1] - 0.6 * r1 * normal[1], p_os[1] + 0.6 * r1 * normal[1]],
                [p_os[0] - 0.6 * r1 * normal[0], p_os[0] + 0.6 * r1 * normal[0]],
                "-",
                color="tab:brown",
                lw=0.8,
                label="overshoot line r2",
            )
            for i, (ex, ey) in enumerate(_cone_edges(port, axis, half[2], 2.0 * r2)):
                a_.plot(
                    ex, ey, "-", color="tab:green", lw=0.8, label="docking cone" if i == 0 else None
                )
    ax.plot([], [], "--", color="0.4", label=f"keep-out r1 = {r1:g} m")
    _finish_lvlh_axes(ax, title or f"{scenario.name}: closed loop")
    _finish_lvlh_axes(ax_z, "approach and docking (target attitude at the end)")
    ax_z.set_aspect("equal", adjustable="box")
    ax_z.set_xlim(-1.6 * r1, 1.6 * r1)
    ax_z.set_ylim(-1.6 * r1, 1.6 * r1)
    ax_d = fig.add_subplot(grid[0, 2])
    from rvdjax.families.phases import target_state

    port_t = np.asarray(target_state(params, t[:, None])[0])[:, 0] if len(t) else np.zeros((0, 3))
    port_distance = np.linalg.norm(x[:, :3] - port_t, axis=1)
    ax_d.semilogy(t, np.maximum(port_distance, 1e-3), color="k")
    ax_d.set_ylabel("distance to port [m]")
    ax_d.grid(alpha=0.3, which="both")
    ax_u = fig.add_subplot(grid[1, 2])
    dv = np.linalg.norm(u, axis=1)
    for k in range(3):
        sel = phase == k
        width = np.asarray(params.ts)[phase[sel]] * 0.8
        ax_u.bar(t[sel], dv[sel], width=width, color=colors[k])
    ax_u.set_xlabel("time [s]")
    ax_u.set_ylabel("|delta-v| per step [m/s]")
    ax_u.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def firing_timeline(path, scenario, infos, title: str | None = None):
    """The valve pulses of a run with thrusters: one row of on-bars per thruster over time.

    Args:
        infos: the run's StepInfo (leading step axis) with ``pulses`` (steps, T, P) [s].
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
