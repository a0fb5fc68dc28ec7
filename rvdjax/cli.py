"""Command line: ``rvdjax run`` (a scenario in closed loop), ``list``, ``compare``, ``demo``
(one QP), ``bench`` (solver peers; ``--closed-loop``: maneuvers per second in batches)."""

from __future__ import annotations

import argparse
import json
import os
import sys

PLOT_FORMATS = (".png", ".pdf", ".svg", ".jpg", ".jpeg")
SCENARIO_HELP = "scenario name (rvdjax list) or scenario file (.toml, rvdjax scenario show)"


def _one_thread():
    """Keep XLA's CPU backend off Eigen's thread pool (must run before JAX first computes).

    Only real XLA options go into ``XLA_FLAGS``: XLA stops reading the variable at the first
    token it does not know (the folklore ``intra_op_parallelism_threads=1`` is one), so
    everything after it, rvdjax's own options included, would silently be dropped. For
    single-core timings pin the process as well (``taskset -c 0``)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "--xla_cpu_multi_thread_eigen=" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_multi_thread_eigen=false").strip()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _ints(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected integers >= 1, got {text!r}")
    return values


def check_output(path: str | None, option: str, formats: tuple[str, ...] | None = None) -> None:
    """ValueError unless the file ``path`` can be written (:func:`rvdjax.outputs.check_file`:
    a file is created and removed in its directory before any work is done)."""
    from rvdjax.outputs import check_file

    check_file(path, option, formats)


def cmd_demo(args) -> int:
    """Solve the fastmpc-3d first MPC step with both modes and Clarabel; print and plot."""
    import time

    import jax
    import numpy as np

    from rvdjax.peers import solve_clarabel
    from rvdjax.problems import FASTMPC3D, fastmpc3d_first_step
    from rvdjax.qp import split_solution, to_qp
    from rvdjax.solver import SolverSettings, Status, max_violation, solve

    check_output(args.plot, "--plot", PLOT_FORMATS)
    ocp = fastmpc3d_first_step(obstacles=not args.no_obstacles)
    ref = solve_clarabel(to_qp(ocp, soft=False))
    rows = []
    sols = {}
    for mode, settings in (("accurate", SolverSettings()), ("paper", SolverSettings.paper())):
        f = jax.jit(lambda o, s=settings: solve(o, s))
        t0 = time.perf_counter()
        sol = jax.block_until_ready(f(ocp))
        compile_s = time.perf_counter() - t0
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            jax.block_until_ready(f(ocp))
            times.append(time.perf_counter() - t0)
        sols[mode] = sol
        rows.append(
            {
                "solver": f"rvdjax-{mode}",
                "objective": float(sol.objective),
                "rel_gap_to_clarabel": (float(sol.objective) - ref.objective) / abs(ref.objective),
                "iterations": int(sol.iterations),
                "status": Status.name(int(sol.status)),
                "solve_ms": 1e3 * float(np.median(times)),
                "compile_s": compile_s,
                "max_violation": float(max_violation(ocp, sol.u, sol.x)),
            }
        )
    rows.append(
        {
            "solver": "clarabel",
            "objective": ref.objective,
            "rel_gap_to_clarabel": 0.0,
            "iterations": ref.iterations,
            "status": ref.status,
            "solve_ms": ref.solve_ms,
            "compile_s": 0.0,
            "max_violation": None,  # not computed for the reference
        }
    )
    if args.json:
        print(json.dumps({"problem": "fastmpc-3d first MPC step", "rows": rows}, indent=2))
    else:
        print("fastmpc-3d first MPC step (paper 000 Table 1: CW at 705 km, m = 6500 kg, N = 30,")
        print("Ts = 15 s, |u| <= 20 N, two moving spherical keep-out zones linearised about the")
        print("unforced drift path; assumption: obstacles move on straight lines)")
        print(
            f"{'solver':<17}{'objective':>16}{'gap':>11}{'iters':>7}{'status':>11}"
            f"{'ms':>9}{'compile s':>11}"
        )
        for r in rows:
            print(
                f"{r['solver']:<17}{r['objective']:>16.6e}{r['rel_gap_to_clarabel']:>11.2e}"
                f"{r['iterations']:>7}{r['status']:>11}{r['solve_ms']:>9.3f}"
                f"{r['compile_s']:>11.2f}"
            )
        print(
            "Paper mode (fixed kappa = 0.05, 10 Newton steps from a cold start) returns a feasible"
        )
        print("plan that is not optimal: its gap is the price of the fixed iteration budget.")
    if args.plot:
        from rvdjax.plots import plot_plan

        _, x_ref = split_solution(ref.z, ocp.N, ocp.nx, ocp.nu)
        plot_plan(
            args.plot,
            ocp,
            {"rvdjax accurate": sols["accurate"], "rvdjax paper": sols["paper"]},
            obstacles=None if args.no_obstacles else FASTMPC3D,
            clarabel_x=x_ref,
        )
        print(f"plot written to {args.plot}", file=sys.stderr if args.json else sys.stdout)
    return 0


def cmd_list(args) -> int:
    from rvdjax.scenarios import DEFAULT_SCENARIO, SCENARIOS

    width = max(len(name) for name in SCENARIOS) + 2
    for name, sc in SCENARIOS.items():
        mark = " (default)" if name == DEFAULT_SCENARIO else ""
        print(f"{name:<{width}}{sc.description}  [{sc.source}; family {sc.family}]{mark}")
    return 0


def cmd_scenario(args) -> int:
    """``rvdjax scenario show NAME``: a scenario's summary, or its scenario file (``--toml``
    prints it, ``--out FILE`` writes it)."""
    from rvdjax.scenarios import get_scenario
    from rvdjax.scenarios.files import scenario_summary, scenario_to_toml

    check_output(args.out, "--out", (".toml",))
    sc = get_scenario(args.name)
    text = scenario_to_toml(sc)
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write(text)
        note = f"{sc.name} written to {args.out}: edit it, then rvdjax run {args.out}"
        print(note, file=sys.stderr if args.toml else sys.stdout)
    if args.toml:
        print(text, end="")
    elif not args.out:
        print(scenario_summary(sc))
    return 0


def _same_file_scenario(a: str, b: str) -> bool:
    """Two scenario files hold the same scenario (their names and comments aside)."""
    if not (a.endswith(".toml") and b.endswith(".toml")):
        return False
    import dataclasses

    from rvdjax.scenarios import get_scenario
    from rvdjax.scenarios.files import scenario_to_toml

    texts = {scenario_to_toml(dataclasses.replace(get_scenario(n), name="")) for n in (a, b)}
    return len(texts) == 1


def run_scenario(
    name: str,
    mode: str = "accurate",
    truth: str = "linear",
    disturbed: bool = False,
    seed=0,
    study=None,
    run: int = 0,
    nav_filter: bool = False,
    tuned: str | None = None,
    thrusters: bool = False,
):
    """Fly a named scenario once (jitted). Returns (scenario, params, infos, metrics, ms/step).

    ``thrusters``: fly the scenario's thruster set (allocation, modulation, valve pulses in the
    truth) instead of ideal forces.

    ``disturbed``: navigation noise, thrust-amplitude error and minimum impulse bit of the
    scenario's disturbance parameters, drawn from PRNG key ``seed``. ``study``, ``run``: fly
    run ``run`` of the study in directory ``study`` instead (its exact inputs). ``tuned``: a
    tuned-parameters file written by ``rvdjax tune`` (its values replace the scenario's)."""
    import time

    import jax

    from rvdjax.loop import fly
    from rvdjax.scenarios import get_scenario

    if study is not None:  # one run of a study, with exactly the study's inputs
        from rvdjax.study import replay_inputs
        from rvdjax.verify.cli import is_verification
        from rvdjax.verify.cli import replay_inputs as verify_replay

        replay = verify_replay if is_verification(study) else replay_inputs
        spec, sc, loop, params, x0, key, sp = replay(study, run)
        recorded = spec.scenario
        if recorded.endswith(".toml") and not os.path.exists(recorded):  # the study moved
            recorded = os.path.join(study, STUDY_SCENARIO_FILE)
        if spec.scenario != name and not _same_file_scenario(name, recorded):
            raise ValueError(f"run {run} of {study} flies {spec.scenario!r}, not {name!r}")
    else:
        sc = get_scenario(name)
        params, x0 = sc.build(thrusters=thrusters)
        loop = sc.loop(
            mode, truth=truth, disturbed=disturbed, nav_filter=nav_filter, thrusters=thrusters
        )
        sc.check(params, x0, loop)
        sp = sc.solver_params(mode)
        key = jax.random.key(int(seed))
    if tuned is not None:
        from rvdjax.tune import apply_params_file

        params, sp, _ = apply_params_file(tuned, sc, params, sp, mode)
    run = jax.jit(lambda p, x, k, s: fly(loop, p, x, k, s))
    compiled = run.lower(params, x0, key, sp).compile()
    t0 = time.perf_counter()
    infos, metrics = jax.block_until_ready(compiled(params, x0, key, sp))
    wall = time.perf_counter() - t0
    steps = max(int(metrics.steps), 1)
    return sc, params, infos, metrics, 1e3 * wall / steps


def metrics_dict(m) -> dict:
    """A run's metrics as plain JSON values (inf as None)."""
    from rvdjax.loop.metrics import metrics_row

    return metrics_row(m)


def cmd_tune(args) -> int:
    from rvdjax.scenarios import get_scenario
    from rvdjax.study.spec import parse_assignment
    from rvdjax.tune import TuneSpec, parse_loss, parse_names, tunables_of

    sc = get_scenario(args.scenario)
    if args.judge_thrusters and sc.thrusters is None:
        raise ValueError(f"--judge-thrusters: scenario {sc.name!r} has no thruster set")
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
        mode=args.mode,
        disturbed=args.disturbed,
        nav_filter=args.nav_filter,
        initial=args.initial,
        vary=vary,
        n_steps=args.n_steps,
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


def cmd_run(args) -> int:
    from rvdjax.disturbances import DISTURBANCE_NOTES
    from rvdjax.scenarios import get_scenario

    check_output(args.plot, "--plot", PLOT_FORMATS)
    if args.plot and args.thrusters:
        stem, ext = os.path.splitext(args.plot)
        check_output(f"{stem}-firings{ext}", "--plot (its firing timeline)", PLOT_FORMATS)
    scenario = get_scenario(args.scenario)  # unknown names fail before anything is compiled
    if args.thrusters and scenario.thrusters is None:
        raise ValueError(f"--thrusters: scenario {scenario.name!r} has no thruster set")
    if args.thrusters and args.study is not None:
        raise ValueError("--thrusters with --study: a replay flies the study's own set-up")
    if (args.study is None) != (args.run is None):
        raise ValueError("--study DIR and --run R go together (replay run R of a study)")
    if args.nav_filter and not args.disturbed:
        raise ValueError("--nav-filter needs --disturbed (it filters the noisy measurements)")
    sc, params, infos, m, ms_per_step = run_scenario(
        args.scenario,
        args.mode,
        args.truth,
        args.disturbed,
        args.seed,
        args.study,
        args.run,
        args.nav_filter,
        args.params,
        args.thrusters,
    )
    ideal = None
    if args.thrusters:  # the same maneuver with ideal forces, for the side-by-side figures
        ideal = run_scenario(
            args.scenario,
            args.mode,
            args.truth,
            args.disturbed,
            args.seed,
            nav_filter=args.nav_filter,
            tuned=args.params,
        )[3]
    if args.study is not None:
        from rvdjax.study.table import read_config

        cfg = read_config(args.study)["spec"]
        args.mode, args.truth, args.disturbed = cfg["mode"], cfg["truth"], cfg["disturbed"]
        args.nav_filter = cfg["nav_filter"]
        args.thrusters = cfg.get("thrusters", False)
    notes = list(sc.notes(args.mode, thrusters=args.thrusters))
    if args.params is not None:
        notes.append(f"tuned values from {args.params} replace the scenario's (rvdjax tune)")
    if args.disturbed:
        d = params.disturbances
        notes.append(
            DISTURBANCE_NOTES[0].format(
                sigma_pos=float(d.sigma_pos), sigma_vel=float(d.sigma_vel), mib_s=float(d.mib_s)
            )
        )
        if args.nav_filter:
            from rvdjax.loop.navigation import NAV_FILTER_NOTES

            notes.extend(NAV_FILTER_NOTES)
        else:
            notes.append("no navigation filter: the guidance sees the noisy measurements")
    result = {
        "scenario": sc.name,
        "family": sc.family,
        "source": sc.source,
        "device": args.device_used,
        "solver_mode": args.mode,
        "truth": args.truth,
        "disturbed": bool(args.disturbed),
        "nav_filter": bool(args.nav_filter),
        "seed": args.seed if args.disturbed and args.study is None else None,
        "study_run": None if args.study is None else {"study": args.study, "run": args.run},
        "tuned_params": args.params,
        "thrusters": sc.thrusters.describe() if args.thrusters else None,
        **metrics_dict(m),
        "ideal_forces": None if ideal is None else metrics_dict(ideal),
        "delta_v_norm": "sum_k ||dv_k||_2 (force inputs: sum_k ||u_k||_2 dt / m)",
        "mean_solve_ms": ms_per_step,
        "mean_solve_ms_note": "wall time of the jitted closed loop per MPC step, after compile",
        "published": sc.published,
        "paper_kappa": sc.paper_kappa if args.mode == "paper" else None,
        "assumptions": notes,
    }
    comparisons = []
    for key, refs in sc.published.items():
        # with thrusters, the figure as the paper defines it (e.g. paper 002 Eq. 11)
        mine = sc.thruster_metrics.get(key, key) if args.thrusters else key
        ours = result[mine]
        if ours is None:
            continue
        for label, value in refs.items():
            figure = f"{mine} vs {label}"
            comparisons.append((figure, ours, value))
    result["comparison"] = [
        {"figure": f, "rvdjax": ours, "paper": ref, "rel_diff": (ours - ref) / ref}
        for f, ours, ref in comparisons
    ]
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(
            f"{sc.name}: {sc.description} [{sc.source}], solver mode {args.mode}, "
            f"truth {args.truth}"
            + (f", disturbed (seed {args.seed})" if args.disturbed else "")
            + f", device {args.device_used}"
        )
        rows = [
            ("docked", result["docked"], ""),
            ("time to dock", result["time_to_dock_s"], "s"),
            ("total impulse, L1 (per-axis sum)", result["effort_l1_N_s"], "N s"),
            ("total impulse, L2 (vector norm)", result["total_impulse_N_s"], "N s"),
            ("delta-v (L2)", result["delta_v_m_s"], "m/s"),
            ("largest constraint violation (truth)", result["max_violation_m"], "m"),
            ("solver statuses", result["solver_status_counts"], ""),
            ("mean solver iterations / step", result["mean_iterations"], ""),
            ("wall time / MPC step", ms_per_step, "ms"),
        ]
        if ideal is not None:
            rows = _thruster_rows(result, result["ideal_forces"], ms_per_step)
        for label, value, unit in rows:
            text = f"{value:.4g}" if isinstance(value, float) else str(value)
            print(f"  {label:<38}{text} {unit}")
        if comparisons:
            print("  compared with the paper:")
            for f, ours, ref in comparisons:
                print(
                    f"    {f:<44}rvdjax {ours:9.4g}  paper {ref:9.4g}  "
                    f"({100 * (ours - ref) / ref:+.1f} %)"
                )
        print("  assumptions:")
        for a in notes:
            print(f"    - {a}")
    if args.plot:
        sc.family_.plot(args.plot, sc, params, infos)
        print(f"plot written to {args.plot}", file=sys.stderr if args.json else sys.stdout)
        if args.thrusters:
            from rvdjax.plots import firing_timeline

            stem, ext = os.path.splitext(args.plot)
            path = f"{stem}-firings{ext}"
            firing_timeline(path, sc, infos)
            print(
                f"firing timeline written to {path}", file=sys.stderr if args.json else sys.stdout
            )
    return 0


def _thruster_rows(flown: dict, ideal: dict, ms_per_step: float) -> list:
    """Rows (label, "ideal forces | thrusters" text, unit) of a run with thrusters."""

    def cell(v):
        if v is None:
            return "-"
        return f"{v:.5g}" if isinstance(v, float) else str(v)

    def pair(key):
        return f"{cell(ideal[key]):>12} | {cell(flown[key]):<12}"

    rows = [("", f"{'ideal forces':>12} | {'thrusters':<12}", "")]
    for label, key, unit in (
        ("docked", "docked", ""),
        ("time to dock", "time_to_dock_s", "s"),
        ("total impulse, L1 (per-axis sum)", "effort_l1_N_s", "N s"),
        ("total impulse, L2 (vector norm)", "total_impulse_N_s", "N s"),
        ("delta-v (L2)", "delta_v_m_s", "m/s"),
        ("torque impulse |tau| dt", "torque_l1_N_m_s", "N m s"),
        ("largest constraint violation (truth)", "max_violation_m", "m"),
        ("mean solver iterations / step", "mean_iterations", ""),
    ):
        rows.append((label, pair(key), unit))
    for label, key, unit in (
        ("thruster impulse, all thrusters", "thruster_impulse_N_s", "N s"),
        ("propellant", "propellant_kg", "kg"),
        ("valve openings", "valve_openings", ""),
        ("pulses dropped (minimum on-time)", "pulses_dropped", ""),
    ):
        rows.append((label, f"{'':>12} | {cell(flown[key]):<12}", unit))
    rows.append(("wall time / MPC step (thrusters)", ms_per_step, "ms"))
    return rows


def cmd_compare(args) -> int:
    from rvdjax.compare import compare_solvers, format_comparison
    from rvdjax.scenarios import get_scenario

    sc = get_scenario(args.scenario)

    def progress(msg):
        print(msg, file=sys.stderr, flush=True)

    if args.thrusters and sc.thrusters is None:
        raise ValueError(f"--thrusters: scenario {sc.name!r} has no thruster set")
    rows = compare_solvers(
        args.scenario, progress=progress, nmpc=not args.no_nmpc, thrusters=args.thrusters
    )
    if args.json:
        out = {"scenario": sc.name, "device": args.device_used, "published": sc.published}
        print(json.dumps({**out, "rows": rows}, indent=2))
    else:
        print(format_comparison(sc.name, rows, sc.published))
        print(f"device: {args.device_used}")
        print(
            "ms/step: wall time of the closed loop per MPC step (Clarabel: host callback with "
            "the QP assembly); NMPC row: IPOPT calls only; IDVD row: per IPOPT (re-)plan, "
            "incl. the simulation"
        )
    return 0


def cmd_bench(args) -> int:
    from rvdjax.bench import machine_info

    check_output(args.out, "--out", (".json",))

    def progress(msg):
        print(msg, file=sys.stderr, flush=True)

    if args.closed_loop:
        from rvdjax.bench import FAMILY_SCENARIOS, closed_loop_batch_benchmark, format_closed_loop
        from rvdjax.scenarios import get_scenario

        names = args.scenarios.split(",") if args.scenarios else FAMILY_SCENARIOS
        for n in names:
            if args.thrusters and get_scenario(n).thrusters is None:
                raise ValueError(f"--thrusters: scenario {n!r} has no thruster set")
        rows = closed_loop_batch_benchmark(
            names,
            batches=tuple(args.batch or (1, 16, 64, 256)),
            runs=args.runs,
            single_runs=args.single_runs,
            disturbed=args.disturbed,
            mode=args.mode,
            chunk=args.chunk,
            iterations=args.iterations,
            progress=progress,
            thrusters=args.thrusters,
        )
        text = format_closed_loop(rows)
    else:
        from rvdjax.bench import BenchConfig, format_table, run_benchmark

        if args.quick:
            config = BenchConfig(
                batches=(64, 256), horizons=(15, 30), horizon_batch=64, n_peer=8, repeats=2
            )
        else:
            config = BenchConfig()
        overrides = {}
        if args.batch:
            overrides["batches"] = tuple(args.batch)
        if args.horizons:
            overrides["horizons"] = tuple(args.horizons)
        if args.peers is not None:
            overrides["peers"] = tuple(p for p in args.peers.split(",") if p)
        if overrides:
            import dataclasses

            config = dataclasses.replace(config, **overrides)
        rows = run_benchmark(config, progress=progress)
        text = format_table(rows)
    for r in rows:
        r["device"] = args.device_used
    if args.out:
        with open(args.out, "w") as f:
            from rvdjax.provenance import environment  # provenance hook

            doc = {"machine": machine_info(), "provenance": environment(), "rows": rows}
            json.dump(doc, f, indent=1)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        print(f"machine: {machine_info()}")
        print(text)
    return 0


# ------------------------------------------------------------------------------------ study


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


STUDY_SCENARIO_FILE = "scenario.toml"


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
        mode=args.mode,
        disturbed=bool(args.disturbed or kind == "robustness"),
        nav_filter=bool(args.nav_filter),
        thrusters=bool(args.thrusters),
        faults=tuple(_fault(f) for f in (args.fault or ())),
        fdir=not args.no_fdir,
        time_limit_s=args.time_limit_s,
        n_steps=args.n_steps,
        slots=args.slots,
        chunk=args.chunk,
        iterations=args.iterations,
    )


def _distributed(args) -> tuple[int, int]:
    """(process index, process count): jax.distributed when --coordinator is given; with
    ``--coordinator auto`` JAX reads the cluster's environment (Slurm's srun, Open MPI, ...)."""
    if not args.coordinator:
        return 0, 1
    import jax

    if args.coordinator == "auto":
        jax.distributed.initialize(initialization_timeout=120)
        return jax.process_index(), jax.process_count()
    if args.num_processes is None or args.process_id is None:
        raise ValueError("--coordinator needs --num-processes and --process-id")
    jax.distributed.initialize(
        coordinator_address=args.coordinator,
        num_processes=args.num_processes,
        process_id=args.process_id,
        initialization_timeout=120,
    )
    return jax.process_index(), jax.process_count()


def _barrier(name: str, count: int) -> None:
    """Wait for every process of a jax.distributed run (the coordination service's barrier)."""
    if count == 1:
        return
    from jax._src import distributed

    distributed.global_state.client.wait_at_barrier(name, 3_600_000)


def cmd_study(args) -> int:
    from rvdjax.study import format_summary, run_study, summarize

    if args.study_command == "summary":
        s = summarize(args.out)
        print(json.dumps(s, indent=2) if args.json else format_summary(s))
        return 0
    spec = _study_spec(args)
    import dataclasses

    from rvdjax.scenarios import get_scenario

    sc = get_scenario(args.scenario)
    copy = spec.scenario if args.scenario.endswith(".toml") else None  # its copy in --out
    if copy is not None:
        sc = dataclasses.replace(sc, name=copy)
        if args.resume and os.path.exists(copy) and not _same_file_scenario(args.scenario, copy):
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
        _barrier("rvdjax-study-out", count)
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
    _barrier("rvdjax-study-done", count)
    if count > 1:
        import jax

        jax.distributed.shutdown()
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


# Where each command's work runs under --device auto (rvdjax.devices): one maneuver at a time
# on the CPU, batches on JAX's default device (a GPU where there is one).
COMMAND_WORK = {"study": "batch", "verify": "batch"}


def _add_device_option(parser: argparse.ArgumentParser) -> None:
    """``--device auto|cpu|gpu`` on every command (the leaves of the sub-command tree)."""
    from rvdjax import devices as _devices

    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        parser.add_argument(
            "--device",
            choices=_devices.CHOICES,
            default="auto",
            help="where to compute: auto (default: one maneuver on the CPU, batches on a GPU "
            "if there is one), cpu or gpu",
        )
        return
    for action in subs:
        for child in set(action.choices.values()):
            _add_device_option(child)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="rvdjax",
        description="MPC guidance for spacecraft rendezvous and docking (Fast MPC in JAX).",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("list", help="list the named scenarios")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("scenario", help="show a scenario; write it as a file to edit and fly")
    q = p.add_subparsers(dest="scenario_command", required=True).add_parser(
        "show", help="a scenario's values, or its scenario file (--toml, --out)"
    )
    q.add_argument("name", help=SCENARIO_HELP)
    q.add_argument("--toml", action="store_true", help="print the scenario file (TOML)")
    q.add_argument("--out", metavar="FILE", help="write the scenario file to FILE (.toml)")
    q.set_defaults(func=cmd_scenario)

    p = sub.add_parser("run", help="fly a named scenario in closed loop (default fastmpc-3d)")
    p.add_argument("scenario", nargs="?", default="fastmpc-3d", help=SCENARIO_HELP)
    p.add_argument(
        "--mode",
        choices=("accurate", "paper", "barrier"),
        default="accurate",
        help="solver mode (default accurate)",
    )
    p.add_argument(
        "--truth",
        choices=("linear", "two-body", "two-body-j2", "two-body-j2-drag"),
        default="linear",
        help="truth propagation: the model (default) or nonlinear (model mismatch; what each "
        "family supports: rvdjax list)",
    )
    p.add_argument(
        "--disturbed",
        action="store_true",
        help="navigation noise and Gauss-Markov thrust error (paper 003 Ch. 5)",
    )
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of a disturbed run")
    p.add_argument(
        "--nav-filter",
        action="store_true",
        help="with --disturbed: a Kalman filter on the measurements feeds the guidance",
    )
    p.add_argument("--study", metavar="DIR", help="replay a run of the study in DIR (with --run)")
    p.add_argument("--run", type=int, metavar="R", help="the run index to replay (with --study)")
    p.add_argument(
        "--params", metavar="FILE", help="fly the tuned values in FILE (written by rvdjax tune)"
    )
    p.add_argument(
        "--thrusters",
        action="store_true",
        help="fly the vehicle's thrusters (allocation, pulse modulation, valve pulses in the "
        "truth) and print the figures next to the ideal-force run's",
    )
    p.add_argument(
        "--plot",
        metavar="FILE",
        help="write the trajectory plot to FILE (png, pdf); with --thrusters also the firing "
        "timeline to FILE-firings",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "tune",
        help="tune weights by gradient through the closed loop (optax), judged on held-out runs",
    )
    p.add_argument("scenario", help=SCENARIO_HELP)
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
    p.add_argument("--seed", type=int, default=0, help="training-set seed (held-out: seed + 1)")
    p.add_argument("--mode", choices=("accurate", "paper", "barrier"), default="accurate")
    p.add_argument("--disturbed", action="store_true", help="noise and thrust errors")
    p.add_argument("--nav-filter", action="store_true", help="with --disturbed: Kalman filter")
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
    p.add_argument("--n-steps", type=int, help="MPC steps per maneuver (default: the scenario's)")
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
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_tune)

    p = sub.add_parser("compare", help="fly a scenario with every solver (paper 000 Sec. IV)")
    p.add_argument("scenario", nargs="?", default="fastmpc-3d", help=SCENARIO_HELP)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--no-nmpc", action="store_true", help="skip the CasADi/IPOPT baselines")
    p.add_argument(
        "--thrusters",
        action="store_true",
        help="the rvdjax and Clarabel loops fly the vehicle's thrusters (the NMPC and IDVD "
        "baselines keep ideal forces)",
    )
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("demo", help="solve one QP: the fastmpc-3d first MPC step")
    p.add_argument("--plot", metavar="FILE", help="write the planned trajectories to FILE (png)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--no-obstacles", action="store_true", help="drop the keep-out zones")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "bench",
        help="benchmark: QP solves against Clarabel and the peers, or closed-loop maneuvers "
        "per second in batches (--closed-loop)",
    )
    p.add_argument("--json", action="store_true", help="print the rows as JSON")
    p.add_argument("--out", metavar="FILE", help="also write the rows to FILE (.json)")
    p.add_argument("--quick", action="store_true", help="small batches (a smoke run)")
    p.add_argument(
        "--closed-loop",
        action="store_true",
        help="whole maneuvers: one jitted maneuver at a time against the batch engine",
    )
    p.add_argument(
        "--thrusters",
        action="store_true",
        help="closed loop: fly every scenario with ideal forces and with its thrusters in the "
        "same run (slowdown column)",
    )
    p.add_argument(
        "--batch", type=_ints, help="batch sizes (QP: vmapped batches; closed loop: slots)"
    )
    p.add_argument(
        "--scenarios", help="closed loop: comma-separated scenarios (default: one per family)"
    )
    p.add_argument("--runs", type=int, default=256, help="closed loop: runs per batch size")
    p.add_argument(
        "--single-runs",
        type=int,
        default=16,
        help="closed loop: runs flown one at a time for the reference rate",
    )
    p.add_argument(
        "--disturbed",
        action="store_true",
        help="closed loop: navigation noise and thrust error, distinct keys",
    )
    p.add_argument(
        "--mode",
        choices=("accurate", "paper", "barrier"),
        default="accurate",
        help="closed loop: solver mode (default accurate)",
    )
    p.add_argument("--chunk", type=int, default=32, help="closed loop: slots per vmapped chunk")
    p.add_argument(
        "--iterations", type=int, default=3, help="closed loop: solver iterations per slot per tick"
    )
    p.add_argument("--horizons", type=_ints, help="QP: horizons for the scaling rows, e.g. 15,30")
    p.add_argument("--peers", help="QP: comma-separated peers (default: all installed)")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="CPU threads for XLA and the peers (default 1, as in the README)",
    )
    p.set_defaults(func=cmd_bench)

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
        q.add_argument("scenario", help=SCENARIO_HELP)
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
            "--disturbed",
            action="store_true",
            help="navigation noise, thrust error, minimum impulse bit (robustness: always)",
        )
        q.add_argument(
            "--nav-filter", action="store_true", help="Kalman filter on the measurements"
        )
        q.add_argument(
            "--thrusters",
            action="store_true",
            help="fly the vehicle's thrusters (then --vary/--grid also take thruster_thrust_N, "
            "thruster_valve_s, thruster_min_on_s, thruster_isp_s, thruster_magnitude_error[i], "
            "thruster_misalignment[3i+j], thruster_fault_time_s[i])",
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
        q.add_argument("--seed", type=int, default=0, help="study seed (default 0)")
        q.add_argument("--mode", choices=("accurate", "paper", "barrier"), default="accurate")
        q.add_argument(
            "--time-limit-s", type=float, help="a run not docked by then fails (e.g. 12000)"
        )
        q.add_argument("--n-steps", type=int, help="MPC steps at most (default: the scenario's)")
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
        q.add_argument("--json", action="store_true", help="print the summary as JSON")
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
        q.set_defaults(func=cmd_study)
    q = ssub.add_parser("summary", help="summarise a finished (or interrupted) study")
    q.add_argument("out", metavar="DIR")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_study)

    from rvdjax.verify.cli import add_parser as add_verify_parser

    add_verify_parser(sub, SCENARIO_HELP)

    _add_device_option(parser)
    args = parser.parse_args(argv)
    if getattr(args, "threads", 1) == 1:
        _one_thread()
    devices = getattr(args, "devices", 1)
    if devices > 1 and "xla_force_host_platform_device_count" not in os.environ.get(
        "XLA_FLAGS", ""
    ):  # on a CPU, one XLA host device per core asked for (before JAX starts)
        os.environ["XLA_FLAGS"] = (
            f"--xla_force_host_platform_device_count={devices} " + os.environ.get("XLA_FLAGS", "")
        ).strip()
    try:
        # jax.distributed must start before anything else touches JAX (the device choice
        # below does)
        args.processes = _distributed(args) if getattr(args, "coordinator", None) else (0, 1)
        from rvdjax import devices as _devices

        with _devices.placed(args.device, COMMAND_WORK.get(args.command, "single")) as dev:
            args.device_used = _devices.describe(dev)
            return args.func(args)
    except ValueError as err:  # bad user input: say what and stop, no traceback
        print(f"rvdjax {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
