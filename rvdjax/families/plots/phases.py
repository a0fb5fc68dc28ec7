"""The figure of one phases run (the family's ``plot``; matplotlib is imported when it draws,
never by :mod:`rvdjax.families.phases`, which the jitted kernel uses)."""

from __future__ import annotations

import numpy as np

from rvdjax.families.phases import target_state


def plot(path, scenario, params, infos, title: str | None = None):
    """Draw a three-phase thesis run (paper 003): the radial / along-track path coloured by
    phase with the keep-out sphere r1 and the approach cone; a zoom on the approach and
    docking (overshoot line at r2, docking cone at the port, at the final attitude of the
    target); distance to the port (log) and delta-v per step."""
    from rvdjax.plots import cone_edges, finish_lvlh_axes, pyplot, save_figure

    plt = pyplot()

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
        for i, (ex, ey) in enumerate(cone_edges(np.zeros(2), axis, half[0], reach)):
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
            for i, (ex, ey) in enumerate(cone_edges(port, axis, half[2], 2.0 * r2)):
                a_.plot(
                    ex, ey, "-", color="tab:green", lw=0.8, label="docking cone" if i == 0 else None
                )
    ax.plot([], [], "--", color="0.4", label=f"keep-out r1 = {r1:g} m")
    finish_lvlh_axes(ax, title or f"{scenario.name}: closed loop")
    finish_lvlh_axes(ax_z, "approach and docking (target attitude at the end)")
    ax_z.set_aspect("equal", adjustable="box")
    ax_z.set_xlim(-1.6 * r1, 1.6 * r1)
    ax_z.set_ylim(-1.6 * r1, 1.6 * r1)
    ax_d = fig.add_subplot(grid[0, 2])

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
    save_figure(fig, path)
