"""The verification's figures: margin against evaluations per method, the failure region in
2-D projections of xi, the probability estimate against runs, the worst runs flown."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = [
    "margin_curves",
    "failure_region",
    "probability_curves",
    "worst_runs",
    "coverage_intervals",
]


def _plt():
    from rvdjax.plots import pyplot

    plt = pyplot()

    return plt


def margin_curves(path, traces: dict, unit: str, title: str) -> None:
    """Best exact margin found against forward evaluations: the median over the repeats and
    the 10-90 % band, one line per method."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for method, tr in traces.items():
        grid = np.unique(np.concatenate(tr.evals))
        rows = []
        for ev, best in zip(tr.evals, tr.best, strict=True):
            idx = np.searchsorted(ev, grid, side="right") - 1
            rows.append(np.where(idx >= 0, best[np.maximum(idx, 0)], np.nan))
        rows = np.asarray(rows)
        med = np.nanmedian(rows, axis=0)
        ax.plot(grid, med, label=method)
        ax.fill_between(
            grid, np.nanpercentile(rows, 10, axis=0), np.nanpercentile(rows, 90, axis=0), alpha=0.15
        )
    ax.axhline(0.0, color="k", lw=0.8, ls="--")
    ax.set_xlabel("forward evaluations (a gradient counted at its measured cost)")
    ax.set_ylabel(f"best exact margin found [{unit}]")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def failure_region(path, df, names, title: str, max_pairs: int = 6) -> None:
    """Every evaluated xi in 2-D projections of the coordinates that separate the failures
    most (largest |mean xi| of the failing points), coloured by pass / fail."""
    plt = _plt()
    xi = np.stack(df["xi"].to_numpy())
    fail = df["margin"].to_numpy() < 0
    d = xi.shape[1]
    score = np.abs(xi[fail].mean(0)) if fail.any() else np.zeros(d)
    top = list(np.argsort(-score)[: min(4, d)])
    pairs = [(a, b) for i, a in enumerate(top) for b in top[i + 1 :]][:max_pairs] or [(0, 0)]
    cols = min(3, len(pairs))
    rows = int(np.ceil(len(pairs) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.6 * rows), squeeze=False)
    for ax, (a, b) in zip(axes.flat, pairs, strict=False):
        ax.scatter(xi[~fail, a], xi[~fail, b], s=3, c="0.7", label="pass", rasterized=True)
        ax.scatter(xi[fail, a], xi[fail, b], s=8, c="tab:red", label="fail")
        ax.set_xlabel(names[a])
        ax.set_ylabel(names[b])
    for ax in list(axes.flat)[len(pairs) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def probability_curves(path, results: list[dict], title: str) -> None:
    """The estimate and its 95 % interval against runs: running estimates (mc, is) and the
    final estimate of every result."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for res in results:
        h = res.get("history")
        if h:
            h = np.asarray(h, float)
            (line,) = ax.plot(h[:, 0], h[:, 1], label=res["method"])
            ax.fill_between(h[:, 0], h[:, 2], h[:, 3], alpha=0.15, color=line.get_color())
        lo, hi = res["ci95"]
        ax.errorbar(
            [res["runs"]],
            [res["p"]],
            yerr=[[max(res["p"] - lo, 0)], [max(hi - res["p"], 0)]],
            fmt="o",
            capsize=3,
            label=f"{res['method']} (final)",
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("closed-loop runs")
    ax.set_ylabel("P(failure)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def worst_runs(out_dir, pb, xis, runs) -> list[str]:
    """Fly the worst points again (one run each) and draw each with its family's figure."""
    import jax

    from rvdjax.loop import fly

    paths = []
    fam = pb.scenario.guidance_family
    if fam.plot is None:
        return paths
    lay = fam.layout
    run_one = jax.jit(lambda p, x: fly(pb.loop, p, x, pb.key, pb.sp))  # compiled once
    for xi, run in zip(xis, runs, strict=True):
        x0, params = pb.dispersion.apply(np.asarray(xi), pb.x0, pb.params, lay)
        infos, _ = run_one(params, x0)
        path = str(Path(out_dir) / f"worst-run-{int(run)}.png")
        fam.plot(path, pb.scenario, params, jax.tree.map(np.asarray, infos), title=f"run {run}")
        paths.append(path)
    return paths


def coverage_intervals(path, cases: list[dict], title: str) -> None:
    """Each case's seeded estimates with their 95 % intervals against its reference (a
    panel per case: dicts with "label", "estimates" [{"p", "ci95"}], "reference" {"p",
    "ci95"})."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(cases), figsize=(4.2 * len(cases), 3.8), squeeze=False)
    for ax, case in zip(axes[0], cases, strict=True):
        est = case["estimates"]
        ref = case["reference"]
        x = np.arange(len(est))
        p = np.array([e["p"] for e in est])
        lo = np.array([e["ci95"][0] for e in est])
        hi = np.array([e["ci95"][1] if np.isfinite(e["ci95"][1]) else np.nan for e in est])
        hit = (lo <= ref["p"]) & (ref["p"] <= hi)
        ax.axhspan(*ref["ci95"], color="0.85", label="reference, 95 %")
        ax.axhline(ref["p"], color="k", lw=1.0)
        for ok, color in ((True, "C0"), (False, "C3")):
            sel = hit == ok
            ax.errorbar(x[sel], p[sel], yerr=[p[sel] - lo[sel], hi[sel] - p[sel]], fmt="o",
                        ms=3, color=color, lw=1, label="covers" if ok else "misses")  # fmt: skip
        ax.set_yscale("log")
        ax.set_xlabel("seed")
        ax.set_title(f"{case['label']}: {hit.mean():.0%} cover", fontsize=9)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("P(failure)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
