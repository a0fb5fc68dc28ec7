"""``rvdjax tune``: tune the guidance's weights by gradient through the closed loop."""

from __future__ import annotations

import json

from rvdjax.cli.options import add_flight_options, add_json, add_scenario, flight_options

__all__ = ["add_parser", "cmd"]


def add_parser(sub) -> None:
    p = sub.add_parser(
        "tune",
        help="tune weights by gradient through the closed loop (optax), judged on held-out runs",
    )
    add_scenario(p)
    add_flight_options(
        p,
        help={
            "seed": "training-set seed (held-out: seed + 1)",
            "thrusters": "refused: the gradients fly ideal forces (see --judge-thrusters)",
        },
    )
    p.add_argument(
        "--params",
        default="Q,R",
        help="comma-separated values to tune (default Q,R; the family's list: rvdjax tune "
        "SCENARIO --list-params)",
    )
    p.add_argument("--list-params", action="store_true", help="list the tunable values, stop")
    p.add_argument(
        "--loss",
        help="surrogate weights, e.g. effort=1,time=1,margin=10 (the defaults)",
    )
    p.add_argument("--train", type=int, default=16, help="training maneuvers (default 16)")
    p.add_argument("--heldout", type=int, default=64, help="held-out maneuvers (default 64)")
    p.add_argument("--steps", type=int, default=30, help="optimiser steps (default 30)")
    p.add_argument("--lr", type=float, default=0.05, help="Adam step size on theta (0.05)")
    p.add_argument(
        "--initial",
        choices=("nominal", "paper003"),
        default="nominal",
        help="initial-state sampler (default: the scenario's x0, positions x N(1, 0.05))",
    )
    p.add_argument(
        "--vary",
        action="append",
        default=None,
        metavar="NAME=DIST",
        help="initial-state distribution as in rvdjax study (replaces the default), e.g. "
        "x0[0]=*normal(1,0.1)",
    )
    p.add_argument(
        "--no-random-search", action="store_true", help="skip the derivative-free baseline"
    )
    p.add_argument("--search-sigma", type=float, default=0.3, help="random search spread (0.3)")
    p.add_argument(
        "--judge-thrusters",
        action="store_true",
        help="also judge every tuning on the held-out maneuvers flown with the thrusters "
        "(gradients stay on the ideal-force plant)",
    )
    p.add_argument(
        "--no-remat",
        action="store_true",
        help="keep every step's solver residuals instead of recomputing the step (faster "
        "gradient, memory grows with the steps)",
    )
    p.add_argument("--out", metavar="DIR", help="write the tuned values, tables and plots here")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_json(p, "print the summary as JSON")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    from rvdjax.scenarios import get_scenario
    from rvdjax.study.spec import parse_assignment
    from rvdjax.tune import TuneSpec, parse_loss, parse_names, tunables_of

    sc = get_scenario(args.scenario)
    if args.thrusters:
        raise ValueError(
            "--thrusters: tune follows gradients of the ideal-force loop (a pulse train's "
            "derivative is zero almost everywhere); judge the tuning with them: --judge-thrusters"
        )
    if args.judge_thrusters and sc.thrusters is None:
        raise ValueError(f"--judge-thrusters: scenario {sc.name!r} has no thruster set")
    opts = flight_options(args)
    if args.list_params:
        for name, t in tunables_of(sc, args.mode).items():
            print(f"{name:<16}{t.description}")
        return 0
    from rvdjax.outputs import check_dir

    check_dir(args.out, "--out")
    vary = None
    if args.vary:
        vary = tuple(parse_assignment(v, "--vary") for v in args.vary)
    spec = TuneSpec(
        scenario=sc.name,
        params=parse_names(args.params, sc, args.mode),
        loss=parse_loss(args.loss),
        train=args.train,
        heldout=args.heldout,
        steps=args.steps,
        lr=args.lr,
        seed=args.seed,
        mode=opts.mode,
        truth=opts.truth,
        disturbed=opts.disturbed,
        nav_filter=opts.nav_filter,
        initial=args.initial,
        vary=vary,
        n_steps=opts.n_steps,
        time_limit_s=opts.time_limit_s,
        random_search=not args.no_random_search,
        search_sigma=args.search_sigma,
        remat=not args.no_remat,
        judge_thrusters=args.judge_thrusters,
    )
    from rvdjax.tune import tune

    result = tune(spec, out=args.out, progress=not args.quiet)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(
        f"{sc.name}: tuned {', '.join(result['params'])} ({result['n_values']} values) over "
        f"{spec.train} training maneuvers, {spec.steps} Adam steps; loss {spec.loss.label()}"
    )
    print(f"  held-out maneuvers: {spec.heldout}")
    keys = ("effort", "time_to_dock_s", "docked_fraction", "max_violation_m", "loss")
    width = max(16, *(len(label) + 2 for label in result["heldout"]))
    print(f"  {'tuning':<{width}}" + "".join(f"{k:>18}" for k in keys))
    for label, m in result["heldout"].items():
        cells = "".join(f"{'-' if m[k] is None else format(m[k], '.4g'):>18}" for k in keys)
        print(f"  {label:<{width}}{cells}")
    print(f"  effort = {result['heldout']['hand']['effort_metric']}")
    print(
        f"  gradient step {result['grad_step_s']:.3g} s, forward batch {result['forward_s']:.3g}"
        f" s, peak memory {result['peak_memory_mb']:.0f} MB"
        if result["grad_step_s"] is not None
        else f"  forward batch {result['forward_s']:.3g} s"
    )
    if args.out:
        print(
            f"  files: {args.out}/tuned_params.json (rvdjax run {sc.name} --params ...), "
            "history.parquet, heldout.parquet, plots/"
        )
    print("  assumptions:")
    for a in result["assumptions"]:
        print(f"    - {a}")
    return 0
