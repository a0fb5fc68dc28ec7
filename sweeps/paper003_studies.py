"""Paper 003's batch studies (Chapters 4-6) with rvdjax.

    python sweeps/paper003_studies.py ch4 --initial-conditions 500 --out studies/
    python sweeps/paper003_studies.py ch5 --initial-conditions 100 --realisations 60 --out studies/
    python sweeps/paper003_studies.py ch6 --out studies/

* ch4: the sample-time x horizon sweeps of Sec. 4.2-4.4 (rendezvous Ts1 x N1, approach
  Ts2 x N2, docking Ts3 x N3) over the Sec. 4.1 initial conditions, 200-minute limit, failures
  counted. rvdjax flies whole three-phase maneuvers at every point and reads the phase's
  figures (the thesis starts the approach and docking sweeps from the end of a rendezvous with
  N1 = 30, Ts1 = 30 s: the phases before the swept one differ only by their own settings here).
* ch5: the robustness study: initial conditions x noise realisations with the thrust error and
  navigation noise, with and without rvdjax's navigation filter; the average over initial
  conditions of the standard deviation over realisations (the thesis: 4.25 m/s, 19.54 min).
* ch6: solve time per MPC step by phase and N1 (the thesis: 119 / 270 / 864 ms on an emulated
  ARM for N1 = 15 / 30 / 45; compare the ratios).

Every study is resumable (run the same command again with --resume) and writes its table,
figures and summary under --out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

SCENARIO = "thesis-vbar"
LIMIT_S = 200 * 60.0
CH4 = {
    "rendezvous": (("Ts1", (20, 30, 40, 50, 60)), ("N1", (15, 30, 45))),
    "approach": (("Ts2", (5, 10, 15, 20, 25, 30)), ("N2", (5, 15, 30))),
    "docking": (("Ts3", (1, 3, 5, 10)), ("N3", (5, 12, 30))),
}
PAPER_CH4_FAILURES = {"N1=30, Ts1=60": 2, "N1=45, Ts1=50": 1, "N1=45, Ts1=60": 6}
PAPER_CH5 = {"delta_v_std_m_s": 4.25, "time_std_min": 19.54}
PAPER_CH6_MS = {15: 119.0, 30: 270.0, 45: 864.0}


def _n_steps(grid) -> int:
    """MPC steps that fit the 200-minute limit at the shortest swept sample time (x3 phases)."""
    return int(np.ceil(LIMIT_S / 5.0)) + 200


def ch4(args) -> dict:
    from rvdjax.study import StudySpec, run_study, summarize
    from rvdjax.study.figures import study_figures

    out = {}
    for phase, grid in CH4.items():
        if args.phases and phase not in args.phases:
            continue
        spec = StudySpec(
            kind="sweep",
            scenario=SCENARIO,
            n_initial=args.initial_conditions,
            initial="paper003",
            grid=tuple((n, tuple(float(v) for v in vs)) for n, vs in grid),
            time_limit_s=LIMIT_S,
            n_steps=_n_steps(grid),
            slots=args.slots,
            seed=args.seed,
        )
        d = Path(args.out) / f"ch4-{phase}"
        t0 = time.perf_counter()
        timing = run_study(spec, d, resume=args.resume, devices=args.devices)
        s = summarize(d)
        s["plots"] = study_figures(d, d / "figures")
        s["seconds"] = time.perf_counter() - t0
        s["runs_per_s"] = timing["runs_per_s"]
        out[phase] = s
    return out


def ch5(args) -> dict:
    from rvdjax.study import StudySpec, read_table, run_study, summarize

    out = {}
    for filt in (False, True):
        spec = StudySpec(
            kind="robustness",
            scenario=SCENARIO,
            n_initial=args.initial_conditions,
            replicates=args.realisations,
            initial="paper003",
            disturbed=True,
            nav_filter=filt,
            time_limit_s=LIMIT_S,
            n_steps=_n_steps(None),
            slots=args.slots,
            seed=args.seed,
        )
        d = Path(args.out) / f"ch5-{'filter' if filt else 'raw'}"
        timing = run_study(spec, d, resume=args.resume, devices=args.devices)
        s = summarize(d)
        df = read_table(d)
        ok = df[df["docked"]]
        g = ok.groupby("ic")
        s["mean_std_delta_v_m_s"] = float(g["delta_v_m_s"].std(ddof=1).mean())
        s["mean_std_time_min"] = float((g["time_to_dock_s"].std(ddof=1) / 60).mean())
        s["runs_per_s"] = timing["runs_per_s"]
        s["paper"] = PAPER_CH5
        out["filter" if filt else "raw"] = s
    return out


def ch6(args) -> dict:
    """Solve time per MPC step by phase and N1: one maneuver per N1 flown step by step from
    Python (a jitted prepare, solve and advance; the solve timed alone)."""
    import jax

    import rvdjax  # noqa: F401
    from rvdjax.loop.kernel import advance, init, prepare
    from rvdjax.scenarios import FlightOptions, get_scenario
    from rvdjax.solver import solve

    sc = get_scenario(SCENARIO)
    nominal = sc.flight(FlightOptions(n_steps=600))
    params, x0, sp = nominal.params, nominal.x0, nominal.solver_params
    rows, samples = {}, {}
    for n1 in (15, 30, 45):
        loop = sc.flight(nominal.options, config=dict(N=(n1, 15, 12)), check=False).loop
        settings = loop.config.settings
        prep = jax.jit(lambda s, loop=loop: prepare(loop, params, s))
        slv = jax.jit(lambda o, w, settings=settings: solve(o, settings, params=sp, init=w))
        adv = jax.jit(lambda s, p, o, loop=loop: advance(loop, params, sp, s, p, o)[0])
        state = init(loop, params, x0)
        times = {0: [], 1: [], 2: []}
        while bool(state.active):
            p = prep(state)
            sol = jax.block_until_ready(slv(p.ocp, p.warm))  # compile on first use
            t0 = time.perf_counter()
            sol = jax.block_until_ready(slv(p.ocp, p.warm))
            dt = time.perf_counter() - t0
            times[int(getattr(p.guidance, "phase", 0))].append(dt * 1e3)
            state = adv(state, p, sol)
        rows[n1] = {
            ph: {"mean_ms": float(np.mean(v)), "p95_ms": float(np.percentile(v, 95)), "n": len(v)}
            for ph, v in times.items()
            if v
        }
        samples[n1] = times
    _solve_time_histograms(samples, Path(args.out) / "ch6-solve-times.png")
    r0 = rows[15][0]["mean_ms"]
    return {
        "solve_ms": rows,
        "rendezvous_ratio_to_N1_15": {n: rows[n][0]["mean_ms"] / r0 for n in rows},
        "paper_ratio_to_N1_15": {n: v / PAPER_CH6_MS[15] for n, v in PAPER_CH6_MS.items()},
    }


def _solve_time_histograms(samples: dict, path: Path) -> None:
    """Solve-time histograms per phase (columns) and N1 (colours), paper 003 Ch. 6."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    for ph, ax in enumerate(axes):
        for n1, times in samples.items():
            if times[ph]:
                ax.hist(times[ph], bins=20, alpha=0.6, label=f"N1 = {n1}")
        ax.set_title(("rendezvous", "approach", "docking")[ph])
        ax.set_xlabel("solve time per MPC step [ms]")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("chapter", choices=("ch4", "ch5", "ch6"))
    ap.add_argument("--out", default="studies")
    ap.add_argument("--initial-conditions", type=int, default=500)
    ap.add_argument("--realisations", type=int, default=60)
    ap.add_argument("--phases", nargs="*", choices=tuple(CH4))
    ap.add_argument("--slots", type=int, default=256)
    ap.add_argument("--devices", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--resume", action="store_true")
    args = ap.parse_args()
    import os

    if args.devices > 1:
        os.environ["XLA_FLAGS"] = (
            f"--xla_force_host_platform_device_count={args.devices} "
            + os.environ.get("XLA_FLAGS", "")
        )
    import rvdjax  # noqa: F401

    result = {"ch4": ch4, "ch5": ch5, "ch6": ch6}[args.chapter](args)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    path = Path(args.out) / f"{args.chapter}-summary.json"
    from rvdjax.provenance import benchmark_block

    prov = benchmark_block("sweeps/paper003_studies.py", vars(args))
    path.write_text(json.dumps({**result, "provenance": prov}, indent=2, default=str))
    print(json.dumps(result, indent=2, default=str)[:4000])
    print(f"summary: {path}")


if __name__ == "__main__":
    main()
