"""The figures of a tuning run (written to ``OUT/plots``): the training loss per closed-loop
evaluation (gradient against random search), the held-out distributions of the exact metrics
per tuning, and one held-out maneuver flown with the hand and the tuned values. The small
``plot_*`` functions draw into a given axes (the notebook reuses them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = [
    "tuning_figures",
    "plot_loss_history",
    "plot_heldout",
    "plot_trajectories",
    "plot_tradeoff",
    "fly_heldout",
]

_ORDER = ("hand", "tuned", "random_search")
_COLORS = {"hand": "C0", "tuned": "C1", "random_search": "C2", "gradient": "C1", "random": "C2"}
_METHOD_LABELS = {"gradient": "gradient (Adam)", "random": "random search"}
_EFFORT_LABELS = {
    "delta_v_m_s": "delta-v, L2 [m/s]",
    "delta_v_l1_m_s": "delta-v, per-axis L1 [m/s]",
    "effort_l1_N_s": "impulse, per-axis L1 [N s]",
    "total_impulse_N_s": "impulse, L2 [N s]",
}


def _plt():
    from rvdjax.plots import pyplot

    plt = pyplot()

    return plt


def _save(plt, fig, path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)


def effort_label(effort_key: str) -> str:
    """Axis label of a headline effort metric (``Tuner.effort_key``)."""
    return _EFFORT_LABELS.get(effort_key, effort_key)


def _labels(rows) -> list[str]:
    present = {r["tuning"] for r in rows}
    return [t for t in _ORDER if t in present] + sorted(present - set(_ORDER))


# ---------------------------------------------------------------------- the training loss


def plot_loss_history(ax, history) -> None:
    """Training loss versus closed-loop evaluations, per method: each evaluation thin, the
    best so far bold; the hand tuning's loss (the first gradient evaluation) dashed."""
    methods = [m for m in ("gradient", "random") if any(h["method"] == m for h in history)]
    for m in methods:
        hs = sorted((h for h in history if h["method"] == m), key=lambda h: h["evaluations"])
        ev = [h["evaluations"] for h in hs]
        c = _COLORS.get(m)
        ax.plot(ev, [h["loss"] for h in hs], lw=0.8, alpha=0.6, color=c, marker=".", ms=3)
        ax.plot(
            ev,
            [h["best_loss"] for h in hs],
            lw=2.4 if m == "gradient" else 2.0,
            ls="-" if m == "gradient" else (0, (4, 2)),
            color=c,
            label=f"{_METHOD_LABELS.get(m, m)}: best so far",
        )
    hand = [h["loss"] for h in history if h["method"] == "gradient" and h["step"] == 0]
    if hand and np.isfinite(hand[0]):
        ax.axhline(hand[0], ls="--", color="k", lw=1.0, label=f"hand ({hand[0]:.3g})")
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("closed-loop evaluations of the training set")
    ax.set_ylabel("training loss (surrogate)")
    ax.grid(alpha=0.3)
    if methods:
        ax.legend(fontsize=8)


# ---------------------------------------------------------------------- held-out metrics


def plot_heldout(axes, rows, effort_key: str) -> None:
    """Box plots (with the runs as dots) of the held-out effort and time to dock per tuning
    into ``axes`` (two axes). Non-finite values (time to dock of runs that did not dock) are
    dropped; the count of docked runs is in the tick labels."""
    labels = _labels(rows)
    cols = (("effort", effort_label(effort_key), 1.0), ("time_to_dock_s", "time to dock [min]", 60))
    for ax, (col, ylabel, scale) in zip(axes, cols, strict=True):
        data, ticks = [], []
        for lab in labels:
            v = np.asarray([r[col] for r in rows if r["tuning"] == lab], float)
            n = v.size
            v = v[np.isfinite(v)] / scale
            data.append(v)
            ticks.append(f"{lab}\n({v.size}/{n})" if col == "time_to_dock_s" else lab)
        pos = np.arange(1, len(labels) + 1)
        keep = [i for i, d in enumerate(data) if d.size]
        if keep:
            ax.boxplot([data[i] for i in keep], positions=pos[keep], widths=0.5, showfliers=False)
        rng = np.random.default_rng(0)
        for i, (lab, d) in enumerate(zip(labels, data, strict=True)):
            jitter = rng.uniform(-0.12, 0.12, d.size)
            ax.scatter(pos[i] + jitter, d, s=10, alpha=0.6, color=_COLORS.get(lab, f"C{i}"))
        ax.set_xticks(pos, ticks)
        ax.set_xlim(0.4, len(labels) + 0.6)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, axis="y")
    axes[0].set_title("held-out effort")
    axes[1].set_title("held-out time to dock (docked runs / all)")


# ---------------------------------------------------------------------- trajectories


def fly_heldout(tuner, values: dict, rows, run: int = 0) -> dict:
    """{label: (positions (k, 2) of the truth, docked, steps flown)} of held-out ``run`` flown
    with each tuning in ``values``: the active steps' start states and the state after the
    last one (when the run ended before the last step)."""
    import jax
    import jax.numpy as jnp

    from rvdjax.loop import fly

    loop = tuner.loop
    nx = loop.family.layout.nx
    pos = list(loop.family.layout.pos[:2])
    row = next(r for r in rows if r["run"] == run)
    x0 = jnp.asarray([row[f"x0_{j}"] for j in range(nx)], float)
    keys = getattr(tuner, "heldout_keys", None)  # the held-out runs' own noise keys
    key = None
    if loop.config.disturbed:
        key = keys[run] if keys is not None else jax.random.key(0)
    run_fn = jax.jit(lambda p, sp, x: fly(loop, p, x, key, sp))
    out = {}
    for label in [t for t in _ORDER if t in values] + sorted(set(values) - set(_ORDER)):
        vals = {k: jnp.asarray(v) for k, v in values[label].items()}
        p, sp = tuner.space.apply(tuner.params, tuner.sp, vals)
        infos, m = run_fn(p, sp, x0)
        x = np.asarray(infos.x)
        active = np.asarray(infos.active, bool)
        idx = np.flatnonzero(active)
        if idx.size and idx[-1] + 1 < active.size:  # the state after the last flown step
            idx = np.append(idx, idx[-1] + 1)
        out[label] = (x[idx][:, pos], bool(m.docked), int(active.sum()))
    return out


def plot_trajectories(ax, flown: dict, layout=None) -> None:
    """Positions of the truth per tuning (``fly_heldout``), start (circle) and end (square)."""
    for i, (label, (xy, docked, steps)) in enumerate(flown.items()):
        if not len(xy):
            continue
        c = _COLORS.get(label, f"C{i}")
        tag = "docked" if docked else "not docked"
        lw = 3.5 - 1.5 * min(i, 1)  # the first (hand) wider, so that a line on it stays visible
        ax.plot(
            xy[:, 0],
            xy[:, 1],
            color=c,
            lw=lw,
            alpha=0.55 if i == 0 else 1.0,
            label=f"{label} ({steps} steps, {tag})",
        )
        ax.plot(*xy[0], "o", color=c, ms=7, mfc="none")
        ax.plot(*xy[-1], "s", color=c, ms=6)
    names = getattr(layout, "names", ()) or ()
    pos = getattr(layout, "pos", (0, 1))
    if len(names) > max(pos[:2]):
        ax.set_xlabel(f"{names[pos[0]]} [m]")
        ax.set_ylabel(f"{names[pos[1]]} [m]")
    else:
        ax.set_xlabel("position 1 [m]")
        ax.set_ylabel("position 2 [m]")
    ax.plot([], [], "o", color="gray", mfc="none", label="start")
    ax.plot([], [], "s", color="gray", label="end")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


# ---------------------------------------------------------------------- trade-off


def plot_tradeoff(ax, points, hand) -> None:
    """Held-out effort versus time to dock of tunings for several loss weights (``points``:
    [{"label", "effort", "time_to_dock_s"}], joined in order of time) against the hand tuning
    (``hand``, a star). Points lower-left of the star dominate it."""
    pts = [
        p
        for p in points
        if p.get("effort") is not None
        and p.get("time_to_dock_s") is not None
        and np.isfinite(p["effort"])
        and np.isfinite(p["time_to_dock_s"])
    ]
    pts = sorted(pts, key=lambda p: p["time_to_dock_s"])
    if pts:
        t = np.asarray([p["time_to_dock_s"] for p in pts]) / 60.0
        e = np.asarray([p["effort"] for p in pts])
        ax.plot(t, e, "-", color="C1", lw=1.0, alpha=0.7)
        ax.scatter(t, e, color="C1", s=30, zorder=3, label="tuned")
        for ti, ei, p in zip(t, e, pts, strict=True):
            ax.annotate(
                str(p["label"]), (ti, ei), textcoords="offset points", xytext=(4, 4), fontsize=7
            )
    if hand is not None and hand.get("effort") is not None and hand.get("time_to_dock_s"):
        ax.scatter(
            hand["time_to_dock_s"] / 60.0,
            hand["effort"],
            marker="*",
            s=180,
            color="C0",
            zorder=4,
            label=str(hand.get("label", "hand")),
        )
    ax.set_xlabel("mean time to dock, held out [min]")
    ax.set_ylabel("mean effort, held out")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


# ---------------------------------------------------------------------- all of them


def tuning_figures(out, tuner, values: dict, history, rows) -> list[str]:
    """Write loss.png, heldout.png and trajectories.png into ``out/plots``; their paths."""
    plt = _plt()
    directory = Path(out) / "plots"
    directory.mkdir(parents=True, exist_ok=True)
    name = tuner.scenario.name
    paths = []

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    plot_loss_history(ax, history)
    ax.set_title(f"{name}: training loss")
    paths.append(_save(plt, fig, directory / "loss.png"))

    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.2))
    plot_heldout(axes, rows, tuner.effort_key)
    fig.suptitle(f"{name}: {len({r['run'] for r in rows})} held-out maneuvers")
    paths.append(_save(plt, fig, directory / "heldout.png"))

    flown = fly_heldout(tuner, {k: v for k, v in values.items() if k in ("hand", "tuned")}, rows)
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    plot_trajectories(ax, flown, tuner.loop.family.layout)
    ax.set_title(f"{name}: held-out run 0")
    paths.append(_save(plt, fig, directory / "trajectories.png"))
    return paths
