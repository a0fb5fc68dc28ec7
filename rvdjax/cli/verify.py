"""``rvdjax verify worst|probability``: the command line of the verification."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from rvdjax.cli.options import add_flight_options, add_json, add_scenario, flight_options
from rvdjax.verify.replay import KIND

__all__ = ["add_parser", "cmd"]


def add_parser(sub) -> None:
    p = sub.add_parser(
        "verify",
        help="verify a guidance law: worst-case search and failure probabilities",
    )
    vsub = p.add_subparsers(dest="verify_command", required=True)

    def common(q):
        add_scenario(q)
        q.add_argument(
            "--requirement",
            required=True,
            help="keep-out[>=X], entry-cone[>=X], overshoot[>=X], contact-speed<=V, "
            "time-to-dock<=T, effort<=B, docks; comma: min of several of one unit",
        )
        q.add_argument(
            "--dispersion",
            required=True,
            help="'+'-separated: paper003, x0:SP,SV[,SA], mass:S, inertia:S, thrust:S, "
            "misalignment:DEG, nav, thrust-error",
        )
        q.add_argument("--out", required=True, metavar="DIR", help="verification directory")
        q.add_argument("--resume", action="store_true", help="continue the verification in DIR")
        q.add_argument(
            "--allow-code-change",
            action="store_true",
            help="resume or reuse evaluations flown by another code version (rows marked)",
        )
        q.add_argument(
            "--temperature",
            type=float,
            help="tau of the smooth margin (default 10 %% of the initial distance) [m]",
        )
        add_flight_options(
            q, help={"seed": "seed of the methods' draws and of the noise xi does not give"}
        )
        q.add_argument("--plots", action="store_true", help="write the figures to DIR")
        add_json(q, "print the summary as JSON")
        q.add_argument("--quiet", action="store_true", help="no progress bar")
        q.set_defaults(func=cmd)

    q = vsub.add_parser("worst", help="search the dispersions for the worst case")
    common(q)
    q.add_argument("--budget", type=int, required=True, help="forward evaluations per repeat")
    q.add_argument("--repeats", type=int, default=20, help="seeded repeats per method")
    q.add_argument(
        "--methods",
        default="gradient,random,lhs,cma-es",
        help="comma list of gradient, design-point, random, lhs, cma-es",
    )
    q.add_argument("--region", choices=("ball", "box"), default="ball")
    q.add_argument(
        "--radius",
        type=float,
        help="k of the region [sigma] (default: all but 1e-6 of N(0, I): 6.0 in 5-D)",
    )
    q.add_argument("--starts", type=int, default=2, help="gradient starts per repeat")
    q.add_argument(
        "--step", type=float, default=1.0, help="line-search base step [sigma] (x0.5, 1, 2..)"
    )
    q.add_argument("--ladder", type=int, default=4, help="line-search steps per iteration")
    q.add_argument("--popsize", type=int, default=8, help="CMA-ES population")

    q = vsub.add_parser("probability", help="estimate the failure probability")
    common(q)
    q.add_argument("--method", required=True, help="subset, is or mc")
    q.add_argument("--budget", type=int, required=True, help="closed-loop runs at most")
    q.add_argument("--level-size", type=int, help="subset simulation: runs per level and replicate")
    q.add_argument(
        "--replicates",
        type=int,
        default=4,
        help="subset simulation: independent replicates; their spread gives the CoV",
    )


def _problem_spec(args):
    from rvdjax.verify.evaluate import ProblemSpec

    flight = dataclasses.asdict(flight_options(args))  # checked in the flags' words
    del flight["faults"]
    return ProblemSpec(
        scenario=args.scenario,
        requirement=args.requirement,
        dispersion=args.dispersion,
        temperature=args.temperature,
        **flight,
    )


def _prepare(out: Path, config: dict, resume: bool, pb, allow_code_change: bool):
    """The directory's :class:`~rvdjax.verify.store.EvalStore`, after checking that ``out``
    is new, or (``resume``) holds this verification flown by this code version
    (:mod:`rvdjax.provenance`: one line naming what differs)."""
    from rvdjax.outputs import check_dir
    from rvdjax.verify.store import CONFIG, EvalStore, write_json

    check_dir(str(out), "--out")
    config = json.loads(json.dumps(config))  # as read back (tuples become lists)
    path = out / CONFIG
    if path.exists():
        if not resume:
            raise ValueError(
                f"--out {out} already holds a verification; pass --resume to continue it or "
                "choose another directory"
            )
    elif out.exists() and any(out.iterdir()):
        raise ValueError(f"--out {out} exists and is not a verification directory")
    definition = {"problem": pb.definition(), "verification": config}
    store = EvalStore(out, pb.effort_key, definition, allow_code_change)
    write_json(path, config)
    return store


def cmd(args) -> int:
    from rvdjax.outputs import check_dir
    from rvdjax.verify.evaluate import problem_for

    check_dir(args.out, "--out")
    out = Path(args.out)
    pspec = _problem_spec(args)
    if args.verify_command == "worst":
        from rvdjax.verify.worst import SearchSpec

        if not (isinstance(args.budget, int) and args.budget >= 1):
            raise ValueError(f"--budget must be an integer >= 1, got {args.budget}")
        kspec = SearchSpec(
            engine_cost=True,
            methods=tuple(m.strip() for m in args.methods.split(",") if m.strip()),
            budget=args.budget,
            repeats=args.repeats,
            region=args.region,
            radius=args.radius,
            starts=args.starts,
            step=args.step,
            ladder=args.ladder,
            popsize=args.popsize,
            seed=args.seed,
        )
        kspec.check_budget()
    else:
        from rvdjax.verify.probability import ProbabilitySpec

        kspec = ProbabilitySpec(
            method=args.method,
            budget=args.budget,
            level_size=args.level_size,
            replicates=args.replicates,
            seed=args.seed,
        )
    # everything above and the problem's set-up are host-side checks: nothing compiled yet
    pb = problem_for(pspec)
    if args.verify_command == "probability" and kspec.method == "is":
        from rvdjax.verify.importance import check_dim

        check_dim(pb.dim)
    config = {
        KIND: args.verify_command,  # (rvdjax.verify.replay.is_verification)
        "spec": dataclasses.asdict(pspec),
        "method": dataclasses.asdict(kspec),
    }
    store = _prepare(out, config, args.resume, pb, args.allow_code_change)
    if args.verify_command == "worst":
        summary = _worst(pb, kspec, out, args, store)
    else:
        summary = _probability(pb, kspec, out, args, store)
    if args.json:
        print(json.dumps(summary, indent=2))
    return 0


def _replay(out: Path, scenario: str, run) -> str:
    return f"rvdjax run {scenario} --study {out} --run {int(run)}"


def _worst(pb, kspec, out: Path, args, store) -> dict:
    from rvdjax.verify.store import read_evals, write_json
    from rvdjax.verify.worst import search

    kspec = kspec.resolved(pb.dim)
    traces = search(pb, kspec, store, progress=not args.quiet)
    methods = {m: tr.summary() for m, tr in traces.items()}
    worst_m = min(traces, key=lambda m: float(np.min(traces[m].worst_margin)))
    tr = traces[worst_m]
    r = int(np.argmin(tr.worst_margin))
    summary = {
        "scenario": pb.scenario.name,
        "requirement": pb.requirement.label(),
        "unit": pb.requirement.unit,
        "dispersion": pb.dispersion.label(),
        "dim": pb.dim,
        "budget": kspec.budget,
        "repeats": kspec.repeats,
        "methods": methods,
        "worst": {
            "margin": float(tr.worst_margin[r]),
            "method": worst_m,
            "xi": [float(v) for v in tr.worst_xi[r]],
            "run": int(tr.worst_run[r]),
            "replay": _replay(out, args.scenario, tr.worst_run[r]),
        },
        "assumptions": pb.notes()
        + [
            "falsification rate: the fraction of repeats that found an exact margin < 0; "
            "evaluations: forward evaluations up to the first such point (a batch counts whole)",
            f"search region: {kspec.region} of radius {kspec.radius:g} in xi; random draws xi "
            "from the dispersion itself (N(0, I) in the region)",
        ],
        "provenance": store.provenance_summary(),
    }
    write_json(out / "summary.json", summary)
    if args.plots:
        from rvdjax.verify import figures

        title = f"{pb.scenario.name}: {pb.requirement.label()} under {pb.dispersion.label()}"
        curves, region = out / "margin-vs-evaluations.png", out / "failure-region.png"
        figures.margin_curves(curves, traces, pb.requirement.unit, title)
        figures.failure_region(region, read_evals(out), pb.dispersion.names(), title)
        order = np.argsort([float(np.min(t.worst_margin)) for t in traces.values()])
        picks = [list(traces.values())[i] for i in order[:2]]
        xis = [t.worst_xi[int(np.argmin(t.worst_margin))] for t in picks]
        runs = [t.worst_run[int(np.argmin(t.worst_margin))] for t in picks]
        summary["figures"] = [str(curves), str(region)]
        summary["figures"] += figures.worst_runs(out, pb, xis, runs)
        write_json(out / "summary.json", summary)
    if not args.json:
        _print_worst(summary)
    return summary


def _print_worst(s: dict) -> None:
    print(
        f"verify worst {s['scenario']}: {s['requirement']} [{s['unit']}] under "
        f"{s['dispersion']} ({s['dim']} coordinates); budget {s['budget']} forward evaluations "
        f"x {s['repeats']} repeats"
    )
    print(
        f"  {'method':<14}{'falsified':>10}{'median evals':>14}{'mean evals':>12}"
        f"{'worst margin':>14}{'wall [s]':>10}"
    )
    for m, v in s["methods"].items():
        med = "-" if v["median_evaluations"] is None else f"{v['median_evaluations']:.3g}"
        mean = "-" if v["mean_evaluations"] is None else f"{v['mean_evaluations']:.3g}"
        print(
            f"  {m:<14}{v['falsification_rate']:>10.0%}{med:>14}{mean:>12}"
            f"{v['worst_margin']:>14.4g}{v['wall_s']:>10.1f}"
        )
        if "gradient_cost" in v:
            line = f"a gradient evaluation costs {v['gradient_cost']:.2f} forward ones"
            if "gradient_cost_vs_engine" in v:
                line += f" ({v['gradient_cost_vs_engine']:.2f} x the engine's wall time per run)"
            print(f"  {'':<14}{line}")
            print(
                f"  {'':<14}zeroed back-solves {v['zeroed_backsolves']}, non-finite gradients "
                f"{v['nonfinite_gradients']}"
            )
    w = s["worst"]
    print(f"  worst: margin {w['margin']:.4g} {s['unit']} ({w['method']}) -> {w['replay']}")
    print("  assumptions:")
    for a in s["assumptions"]:
        print(f"    - {a}")
    _print_provenance(s["provenance"])


def _print_provenance(block) -> None:
    from rvdjax.provenance import summary_lines

    print("  provenance:")
    for line in summary_lines(block):
        print(f"    - {line}")


def _probability(pb, kspec, out: Path, args, store) -> dict:
    from rvdjax.verify.probability import estimate
    from rvdjax.verify.store import read_evals, write_json

    res = estimate(pb, kspec, store, progress=not args.quiet)
    summary = {
        "scenario": pb.scenario.name,
        "requirement": pb.requirement.label(),
        "dispersion": pb.dispersion.label(),
        "dim": pb.dim,
        **{k: v for k, v in res.items() if k not in ("history",)},
        "assumptions": pb.notes(),
        "provenance": store.provenance_summary(),
    }
    write_json(out / "summary.json", {**summary, "history": res.get("history")})
    if args.plots:
        from rvdjax.verify import figures

        req, disp = pb.requirement.label(), pb.dispersion.label()
        title = f"{pb.scenario.name}: P({req} fails) under {disp}"
        figures.probability_curves(out / "estimate-vs-runs.png", [res], title)
        names = pb.dispersion.names()
        figures.failure_region(out / "failure-region.png", read_evals(out), names, title)
    if not args.json:
        ci = summary["ci95"]
        cov = "-" if summary["cov"] is None else f"{summary['cov']:.3g}"
        print(
            f"verify probability {summary['scenario']}: P({summary['requirement']} fails) under "
            f"{summary['dispersion']} by {summary['method']}: p = {summary['p']:.4g}, CoV {cov}, "
            f"95 % interval [{ci[0]:.3g}, {ci[1]:.3g}], {summary['runs']} runs in "
            f"{summary['wall_s']:.1f} s"
        )
        if summary.get("stages"):  # importance sampling: the proposal's stages
            parts = [
                f"{'final ' if st.get('final') else ''}{st['draws']} ({st['failures']} failing)"
                for st in summary["stages"]
            ]
            print(f"  stages: {', '.join(parts)}; only the final stage is counted")
            ess = summary.get("ess_failing") or 0.0
            if 0 < ess < 10:
                print(
                    f"  the estimate rests on {ess:.1f} effective failing draws (a scattered "
                    "failure set): its interval is wide; subset simulation or Monte Carlo may "
                    "be cheaper here"
                )
        if "runs_for_cov_0.3" in summary:
            print(f"  runs for a CoV of 0.3: {summary['runs_for_cov_0.3']}")
        print("  assumptions:")
        for a in summary["assumptions"]:
            print(f"    - {a}")
        _print_provenance(summary["provenance"])
    return summary
