"""The figure of one rendezvous run (the family's ``plot``; matplotlib is imported when it draws,
never by :mod:`rvdjax.families.rendezvous`, which the jitted kernel uses)."""

from __future__ import annotations

import numpy as np


def plot(path, scenario, params, infos, title: str | None = None):
    """Draw one rendezvous run: path with keep-out snapshots, thrust, range and margins.

    Args:
        path: output file.
        scenario: the :class:`rvdjax.scenarios.Scenario` (for the title).
        params: its :class:`rvdjax.families.rendezvous.Params`.
        infos: the run's :class:`rvdjax.loop.StepInfo` (leading axis: step).
    """
    from rvdjax.plots import finish_lvlh_axes, pyplot, save_figure

    plt = pyplot()

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
    finish_lvlh_axes(ax, title or f"{scenario.name}: closed loop")

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
    save_figure(fig, path)
