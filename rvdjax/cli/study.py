"""``rvdjax study montecarlo|sweep|robustness|summary``: batch studies (paper 003 Ch. 4-6)."""

from __future__ import annotations

import json
import os

from rvdjax.cli.options import add_flight_options, add_json, add_scenario, flight_options
from rvdjax.study.spec import STUDY_SCENARIO_FILE

__all__ = ["add_parser", "cmd"]


def add_parser(sub) -> None:
    p = sub.add_parser(
        "study",
        help="batch studies: Monte Carlo, parameter sweeps, robustness (paper 003 Ch. 4-6)",
    )
    ssub = p.add_subparsers(dest="study_command", required=True)
    for kind, text in (
        ("montecarlo", "runs over initial conditions, parameters and disturbances"),
        ("sweep", "a grid of parameter values (horizons, sample times, ...), runs per point"),
        ("robustness", "initial conditions x noise realisations (paper 003 Ch. 5)"),
    ):
        q = ssub.add_parser(kind, help=text)
        add_scenario(q)
        add_flight_options(
            q,
            help={
                "disturbed": "navigation noise, thrust error, minimum impulse bit "
                "(robustness: always)",
                "thrusters": "fly the vehicle's thrusters (then --vary/--grid also take "
                "thruster_thrust_N, thruster_valve_s, thruster_min_on_s, thruster_isp_s, "
                "thruster_magnitude_error[i], thruster_misalignment[3i+j], "
                "thruster_fault_time_s[i])",
                "seed": "study seed (default 0)",
            },
        )
        add_json(q, "print the summary as JSON")
        if kind == "montecarlo":
            q.add_argument("--runs", type=int, default=100, help="number of runs (default 100)")
        if kind == "sweep":
            q.add_argument(
                "--grid",
                action="append",
                metavar="NAME=V1,V2,...",
                help="a swept parameter (repeat for a Cartesian grid); horizons (N, N1) "
                "compile once per value",
            )
            q.add_argument("--runs-per-point", type=int, default=20, help="runs per sweep point")
        if kind == "robustness":
            q.add_argument("--initial-conditions", type=int, default=100)
            q.add_argument("--realisations", type=int, default=60, help="noise keys per state")
        q.add_argument(
            "--vary",
            action="append",
            metavar="NAME=DIST",
            help="draw a parameter per run: uniform(a,b), normal(m,s), +normal(0,s) (added), "
            "*normal(1,s) (scaled), loguniform(a,b), choice(v1,...); NAME: x0, x0[k], "
            "or a physical value (mass, u_max, ts[0], ...)",
        )
        q.add_argument(
            "--initial",
            choices=("nominal", "paper003"),
            default="nominal",
            help="initial states: the scenario's, or paper 003 Sec. 4 (0.15-2.5 km, no-drift "
            "velocity + N(0, 0.5 m/s))",
        )
        q.add_argument(
            "--fault",
            action="append",
            metavar="I:KIND[:T]",
            help="with --thrusters: thruster I stuck-off or stuck-on from T seconds (default 0) "
            "in every run; the allocation knows it from its onset (FDIR) unless --no-fdir",
        )
        q.add_argument(
            "--no-fdir",
            action="store_true",
            help="with --fault: the allocation does not know the fault (it goes unnoticed)",
        )
        q.add_argument("--slots", type=int, help="runs in flight (default: chosen for the device)")
        q.add_argument(
            "--chunk", type=int, help="slots per vmapped chunk (default: chosen for the device)"
        )
        q.add_argument(
            "--iterations", type=int, help="solver iterations per tick (default: for the device)"
        )
        q.add_argument("--out", required=True, metavar="DIR", help="study directory")
        q.add_argument("--resume", action="store_true", help="continue the study in DIR")
        q.add_argument(
            "--allow-code-change",
            action="store_true",
            help="resume a study flown by another code version (new rows marked)",
        )
        q.add_argument("--plots", metavar="DIR", help="write the study's figures to DIR")
        q.add_argument("--quiet", action="store_true", help="no progress bar")
        q.add_argument(
            "--coordinator",
            metavar="HOST:PORT",
            help="jax.distributed coordinator: this process flies its share of the runs "
            "(auto: from the cluster's environment, e.g. under Slurm's srun)",
        )
        q.add_argument(
            "--devices",
            type=int,
            default=1,
            help="shard the slots over N devices (CPU: N host devices, one per core)",
        )
        q.add_argument(
            "--flush-rows",
            type=int,
            help="runs per Parquet part (default 256, or 1/64 of a large study)",
        )
        q.add_argument("--num-processes", type=int)
        q.add_argument("--process-id", type=int)
        q.set_defaults(func=cmd)
    q = ssub.add_parser("summary", help="summarise a finished (or interrupted) study")
    q.add_argument("out", metavar="DIR")
    add_json(q, "print the summary as JSON")
    q.set_defaults(func=cmd)


def _grid(text: str):
    from rvdjax.study.spec import parse_assignment

    name, values = parse_assignment(text, "--grid")
    try:
        vals = tuple(float(v) for v in values.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"--grid {name}: values must be numbers, got {values!r}") from None
    return name, vals


def _fault(text: str) -> tuple:
    """--fault I:KIND[:T] -> (index, kind, time [s])."""
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise ValueError(f"--fault expects INDEX:stuck-off|stuck-on[:TIME_S], got {text!r}")
    try:
        index = int(parts[0])
        when = float(parts[2]) if len(parts) == 3 else 0.0
    except ValueError:
        raise ValueError(
            f"--fault expects INDEX:stuck-off|stuck-on[:TIME_S], got {text!r}"
        ) from None
    return index, parts[1], when


def _study_scenario(args) -> str:
    """The scenario a study records: a built-in's name, or for a scenario file the absolute
    path of the copy the study keeps in its directory (DIR/scenario.toml). The study flies,
    resumes, summarises and replays that copy, whatever happens later to the original file."""
    if not args.scenario.endswith(".toml"):
        return args.scenario
    return os.path.join(os.path.abspath(args.out), STUDY_SCENARIO_FILE)


def _study_spec(args):
    from rvdjax.scenarios import get_scenario
    from rvdjax.study import StudySpec
    from rvdjax.study.spec import parse_assignment

    get_scenario(args.scenario)
    kind = args.study_command
    if kind == "montecarlo":
        n_initial, replicates, grid = args.runs, 1, ()
    elif kind == "sweep":
        if not args.grid:
            raise ValueError("study sweep needs at least one --grid NAME=V1,V2,...")
        n_initial, replicates, grid = args.runs_per_point, 1, tuple(_grid(g) for g in args.grid)
    else:
        n_initial, replicates, grid = args.initial_conditions, args.realisations, ()
    vary = tuple(parse_assignment(v, "--vary") for v in (args.vary or ()))
    opts = flight_options(args, disturbed=bool(args.disturbed or kind == "robustness"))
    for name, value in (("--runs", n_initial), ("--realisations", replicates)):
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    return StudySpec(
        kind=kind,
        scenario=_study_scenario(args),
        n_initial=n_initial,
        replicates=replicates,
        seed=args.seed,
        initial=args.initial,
        vary=vary,
        grid=grid,
        mode=opts.mode,
        truth=opts.truth,
        disturbed=opts.disturbed,
        nav_filter=opts.nav_filter,
        thrusters=bool(opts.thrusters),
        faults=tuple(_fault(f) for f in (args.fault or ())),
        fdir=not args.no_fdir,
        time_limit_s=opts.time_limit_s,
        n_steps=opts.n_steps,
        slots=args.slots,
        chunk=args.chunk,
        iterations=args.iterations,
    )


def cmd(args) -> int:
    from rvdjax.study import format_summary, run_study, summarize

    if args.study_command == "summary":
        s = summarize(args.out)
        print(json.dumps(s, indent=2) if args.json else format_summary(s))
        return 0
    spec = _study_spec(args)
    import dataclasses

    from rvdjax import distributed
    from rvdjax.scenarios import get_scenario
    from rvdjax.scenarios.files import same_scenario

    sc = get_scenario(args.scenario)
    copy = spec.scenario if args.scenario.endswith(".toml") else None  # its copy in --out
    if copy is not None:
        sc = dataclasses.replace(sc, name=copy)
        if args.resume and os.path.exists(copy) and not same_scenario(args.scenario, copy):
            raise ValueError(
                f"{args.scenario} is not the scenario the study in {args.out} flies ({copy}); "
                f"resume it with {copy} as the scenario"
            )
    spec.validate(sc)
    from rvdjax.outputs import check_dir

    check_dir(args.out, "--out")  # proven writable before flying; created after
    check_dir(args.plots, "--plots")
    index, count = args.processes
    if count > 1 or copy is not None:  # process 0 checks --out, writes the configuration
        from rvdjax.study.runner import prepare_out  # (and the scenario file's copy) first

        if index == 0:
            prepare_out(spec, args.out, args.resume, args.allow_code_change, sc)
            if copy is not None and not os.path.exists(copy):
                with open(args.scenario, encoding="utf-8") as f:
                    text = f.read()
                with open(copy + ".tmp", "w", encoding="utf-8") as f:
                    f.write(text)
                os.replace(copy + ".tmp", copy)
        distributed.barrier("rvdjax-study-out", count)
    timing = run_study(
        spec,
        args.out,
        resume=args.resume,
        progress=not args.quiet,
        process_index=index,
        process_count=count,
        devices=args.devices,
        flush_rows=args.flush_rows,
        prepare=count == 1 and copy is None,
        allow_code_change=args.allow_code_change,
    )
    distributed.barrier("rvdjax-study-done", count)
    distributed.shutdown(count)
    if index != 0:
        return 0
    s = summarize(args.out)
    s.update(
        runs_flown=timing["runs_flown"],
        runs_skipped=timing["runs_skipped"],
        seconds=timing["seconds"],
        runs_per_s=timing["runs_per_s"],
        peak_memory_mb=timing["peak_memory_mb"],
        processes=count,
        table=os.path.join(args.out, "runs"),
        engine=timing["engine"],
        outside_device_share=timing["outside_device_share"],
        outside_device_share_flying=timing["outside_device_share_flying"],
        compile_s=timing["compile_s"],
    )
    if args.plots:
        from rvdjax.study.figures import study_figures

        s["plots"] = study_figures(args.out, args.plots)
    if args.json:
        print(json.dumps(s, indent=2))
    else:
        print(format_summary(s))
        print(
            f"  {timing['runs_flown']} runs flown in {timing['seconds']:.1f} s "
            f"({timing['runs_per_s']:.2f} runs/s), peak memory {timing['peak_memory_mb']:.0f} MB; "
            f"table: {s['table']}"
        )
        print(
            f"  device busy {1 - timing['outside_device_share']:.0%} of the wall time "
            f"({1 - timing['outside_device_share_flying']:.0%} without the "
            f"{timing['compile_s']:.1f} s of compiles)"
        )
        for text in timing["engine"]:
            print(f"  engine: {text}")
    return 0
