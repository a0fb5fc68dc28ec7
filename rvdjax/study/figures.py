"""The paper's figures from a study table (paper 003 Figs. 4.2-4.12, 5.x): effort versus time
to dock, effort versus control intervals, failures per sweep point, and the spread per initial
condition of a robustness study."""

from __future__ import annotations

from pathlib import Path

from rvdjax.study.spec import StudySpec
from rvdjax.study.table import read_config, read_table

__all__ = ["study_figures", "scatter_effort_time", "effort_intervals", "failures_per_point"]


def _plt():
    from rvdjax.plots import pyplot

    plt = pyplot()

    return plt


def _panels(spec: StudySpec):
    """[(panel title, [(point index, label), ...]), ...]: with two or more grid parameters
    one panel per value of the last (the thesis draws one figure per horizon, Figs. 4.4-4.12,
    its series the sample times); otherwise one panel with every point."""
    if len(spec.points) == 1:  # a study without a grid has one point, "nominal"
        return [("", [(spec.points[0].index, spec.scenario)])]
    if len(spec.grid) < 2:
        return [("", [(p.index, p.label()) for p in spec.points])]
    last = spec.grid[-1][0]
    panels = []
    for v in spec.grid[-1][1]:
        pts = [p for p in spec.points if p.values[last] == v]
        rest = [
            (p.index, ", ".join(f"{k}={x:g}" for k, x in p.values.items() if k != last))
            for p in pts
        ]
        panels.append((f"{last} = {v:g}", rest))
    return panels


def _scatter_panels(df, spec: StudySpec, x, y, xlabel, ylabel, title, path) -> str:
    """One scatter panel per :func:`_panels` entry, docked runs only, shared axes, the
    points of a panel coloured along viridis (a sweep has more points than a qualitative
    palette has colours)."""
    plt = _plt()
    panels = _panels(spec)
    n = len(panels)
    fig, axes = plt.subplots(
        1, n, figsize=(max(6.4, 4.2 * n), 4.4), sharex=True, sharey=True, squeeze=False
    )
    ok = df["docked"].to_numpy()
    point = df["point"].to_numpy()
    cmap = plt.get_cmap("viridis")
    for ax, (name, series) in zip(axes[0], panels, strict=True):
        for j, (g, label) in enumerate(series):
            sel = ok & (point == g)
            colour = cmap(j / max(len(series) - 1, 1) * 0.9)
            ax.scatter(x[sel], y[sel], s=8, color=colour, label=label)
        ax.set_xlabel(xlabel)
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
        if len(series) > 1:
            ax.legend(fontsize=7, markerscale=2)
    axes[0][0].set_ylabel(ylabel)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)


def scatter_effort_time(df, spec: StudySpec, path) -> str:
    """Effort versus time to dock per docked run, one colour per sweep point (Fig. 4.2b)."""
    ok = df["docked"].to_numpy()
    return _scatter_panels(
        df,
        spec,
        df["time_to_dock_s"].to_numpy() / 60.0,
        df["effort"].to_numpy(),
        "time to dock [min]",
        _effort_label(df),
        f"{spec.scenario}: {int(ok.sum())} of {len(df)} runs docked",
        path,
    )


_EFFORT_LABELS = {
    "delta_v_m_s": "delta-v [m/s]",
    "effort_l1_N_s": "impulse, per-axis L1 [N s]",
    "total_impulse_N_s": "impulse, L2 [N s]",
}


def _effort_label(df) -> str:
    """The label of the ``effort`` column: the metric column it copies."""
    for col, label in _EFFORT_LABELS.items():
        if col in df and df["effort"].equals(df[col]):
            return label
    return "effort"


def effort_intervals(df, spec: StudySpec, path, phase: int | None = None) -> str:
    """Effort (of ``phase``, or the whole run) versus the number of control intervals
    (Figs. 4.4-4.12 right-hand panels)."""
    if phase is not None and f"phase{phase}_intervals" in df:
        x, y = df[f"phase{phase}_intervals"], df[f"phase{phase}_delta_v_m_s"]
        xlabel, ylabel = f"control intervals in phase {phase}", f"phase {phase} delta-v [m/s]"
    else:
        x, y = df["steps"], df["effort"]
        xlabel, ylabel = "control intervals (MPC steps)", _effort_label(df)
    title = spec.scenario if phase is None else f"{spec.scenario}: phase {phase}"
    return _scatter_panels(df, spec, x.to_numpy(), y.to_numpy(), xlabel, ylabel, title, path)


def failures_per_point(df, spec: StudySpec, path) -> str:
    """Failed runs (not docked, or a truth constraint violated) per sweep point."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(6.4, 0.45 * len(spec.points)), 4.0))
    labels, fails = [], []
    for p in spec.points:
        sub = df[df["point"] == p.index]
        labels.append(p.label())
        fails.append(int((sub["failure"] != "").sum()))
    ax.bar(range(len(labels)), fails)
    ax.set_xticks(range(len(labels)), labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(f"failed runs (of {spec.runs_per_point})")
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)


def spread_per_initial_condition(df, spec: StudySpec, path) -> str:
    """Robustness: the standard deviation over noise realisations of effort and time to dock,
    per initial condition (paper 003 Ch. 5 reports their averages)."""
    plt = _plt()
    ok = df[df["docked"]]
    g = ok.groupby("ic")
    sd = g["effort"].std(ddof=1).dropna()
    st = (g["time_to_dock_s"].std(ddof=1) / 60.0).dropna()
    fig, axes = plt.subplots(1, 2, figsize=(9.6, 3.8))
    axes[0].hist(sd, bins=20)
    axes[0].set_xlabel("std of effort per initial condition")
    axes[0].set_title(f"mean {sd.mean():.3g}" if len(sd) else "no docked runs")
    axes[1].hist(st, bins=20)
    axes[1].set_xlabel("std of time to dock per initial condition [min]")
    axes[1].set_title(f"mean {st.mean():.3g} min" if len(st) else "no docked runs")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)


def study_figures(out, directory) -> list[str]:
    """Every figure that fits the study in ``out``, written to ``directory`` (PNG)."""
    out, directory = Path(out), Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    spec = StudySpec.from_dict(read_config(out)["spec"])
    df = read_table(out)
    paths = [
        scatter_effort_time(df, spec, directory / "effort_vs_time.png"),
        effort_intervals(df, spec, directory / "effort_vs_intervals.png"),
    ]
    if any(f"phase{k}_intervals" in df for k in range(3)):
        for k in range(3):
            if f"phase{k}_intervals" in df:
                paths.append(
                    effort_intervals(df, spec, directory / f"phase{k}_vs_intervals.png", k)
                )
    if len(spec.points) > 1:
        paths.append(failures_per_point(df, spec, directory / "failures_per_point.png"))
    if spec.replicates > 1:
        paths.append(spread_per_initial_condition(df, spec, directory / "spread_per_ic.png"))
    return paths
