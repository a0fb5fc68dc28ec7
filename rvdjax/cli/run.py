"""``rvdjax run``: fly a scenario once in closed loop, print its figures beside the paper's."""

from __future__ import annotations

import json
import os
import sys

from rvdjax.cli.options import (
    PLOT_FORMATS,
    add_flight_options,
    add_json,
    add_scenario,
    flight_options,
)

__all__ = ["add_parser", "cmd"]


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="fly a named scenario in closed loop (default fastmpc-3d)")
    add_scenario(p, default="fastmpc-3d")
    add_flight_options(
        p,
        help={
            "seed": "PRNG seed of a disturbed run (default 0)",
            "thrusters": "fly the vehicle's thrusters (allocation, pulse modulation, valve "
            "pulses in the truth) and print the figures next to the ideal-force run's",
        },
    )
    p.add_argument("--study", metavar="DIR", help="replay a run of the study in DIR (with --run)")
    p.add_argument("--run", type=int, metavar="R", help="the run index to replay (with --study)")
    p.add_argument(
        "--params", metavar="FILE", help="fly the tuned values in FILE (written by rvdjax tune)"
    )
    p.add_argument(
        "--plot",
        metavar="FILE",
        help="write the trajectory plot to FILE (png, pdf); with --thrusters also the firing "
        "timeline to FILE-firings",
    )
    add_json(p)
    p.set_defaults(func=cmd)


def _replay(name: str, study: str, run: int):
    """The flight of run ``run`` of the study (or verification) in ``study``."""
    from rvdjax.scenarios.files import same_scenario
    from rvdjax.study import replay
    from rvdjax.study.spec import STUDY_SCENARIO_FILE
    from rvdjax.verify.replay import is_verification
    from rvdjax.verify.replay import replay as verify_replay

    spec, flight = (verify_replay if is_verification(study) else replay)(study, run)
    recorded = spec.scenario
    if recorded.endswith(".toml") and not os.path.exists(recorded):  # the study moved
        recorded = os.path.join(study, STUDY_SCENARIO_FILE)
    if spec.scenario != name and not same_scenario(name, recorded):
        raise ValueError(f"run {run} of {study} flies {spec.scenario!r}, not {name!r}")
    return flight


def _tuned(flight, path: str | None):
    if path is None:
        return flight
    from rvdjax.tune import apply_params_file

    params, sp, _ = apply_params_file(
        path, flight.scenario, flight.params, flight.solver_params, flight.options.mode
    )
    return flight.replace(params=params, solver_params=sp)


def cmd(args) -> int:
    from rvdjax.disturbances import DISTURBANCE_NOTES
    from rvdjax.loop.metrics import metrics_row
    from rvdjax.outputs import check_file
    from rvdjax.scenarios import get_scenario

    check_file(args.plot, "--plot", PLOT_FORMATS)
    if args.plot and args.thrusters:
        stem, ext = os.path.splitext(args.plot)
        check_file(f"{stem}-firings{ext}", "--plot (its firing timeline)", PLOT_FORMATS)
    scenario = get_scenario(args.scenario)  # unknown names fail before anything is compiled
    if (args.study is None) != (args.run is None):
        raise ValueError("--study DIR and --run R go together (replay run R of a study)")
    if args.thrusters and args.study is not None:
        raise ValueError("--thrusters with --study: a replay flies the study's own set-up")
    if args.study is not None:
        flight = _replay(args.scenario, args.study, args.run)
    else:
        flight = scenario.flight(flight_options(args))
    flight = _tuned(flight, args.params)
    sc, opts = flight.scenario, flight.options
    infos, m, ms_per_step = flight.fly_timed()
    ideal = None
    if args.thrusters:  # the same maneuver with ideal forces, for the side-by-side figures
        ideal = _tuned(sc.flight(opts.replace(thrusters=False)), args.params).fly_timed()[1]
    notes = list(flight.notes())
    if args.params is not None:
        notes.append(f"tuned values from {args.params} replace the scenario's (rvdjax tune)")
    if opts.disturbed:
        d = flight.params.plant.disturbances
        notes.append(
            DISTURBANCE_NOTES[0].format(
                sigma_pos=float(d.sigma_pos), sigma_vel=float(d.sigma_vel), mib_s=float(d.mib_s)
            )
        )
        if opts.nav_filter:
            from rvdjax.loop.navigation import NAV_FILTER_NOTES

            notes.extend(NAV_FILTER_NOTES)
        else:
            notes.append("no navigation filter: the guidance sees the noisy measurements")
    tset = flight.thruster_set
    result = {
        "scenario": sc.name,
        "family": sc.family,
        "source": sc.source,
        "device": args.device_used,
        "solver_mode": opts.mode,
        "truth": opts.truth,
        "disturbed": bool(opts.disturbed),
        "nav_filter": bool(opts.nav_filter),
        "seed": opts.seed if opts.disturbed and args.study is None else None,
        "study_run": None if args.study is None else {"study": args.study, "run": args.run},
        "tuned_params": args.params,
        "thrusters": None if tset is None else tset.describe(),
        **metrics_row(m),
        "ideal_forces": None if ideal is None else metrics_row(ideal),
        "delta_v_norm": "sum_k ||dv_k||_2 (force inputs: sum_k ||u_k||_2 dt / m)",
        "mean_solve_ms": ms_per_step,
        "mean_solve_ms_note": "wall time of the jitted closed loop per MPC step, after compile",
        "published": sc.published,
        "paper_kappa": sc.paper_kappa if opts.mode == "paper" else None,
        "assumptions": notes,
    }
    comparisons = []
    for key, refs in sc.published.items():
        # with thrusters, the figure as the paper defines it (e.g. paper 002 Eq. 11)
        mine = sc.thruster_metrics.get(key, key) if tset is not None else key
        ours = result[mine]
        if ours is None:
            continue
        for label, value in refs.items():
            comparisons.append((f"{mine} vs {label}", ours, value))
    result["comparison"] = [
        {"figure": f, "rvdjax": ours, "paper": ref, "rel_diff": (ours - ref) / ref}
        for f, ours, ref in comparisons
    ]
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        _print(sc.description, result, comparisons, notes, ideal is not None, ms_per_step)
    if args.plot:
        sc.guidance_family.plot(args.plot, sc, flight.params, infos)
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


def _print(
    description: str, result: dict, comparisons, notes, side_by_side: bool, ms_per_step: float
) -> None:
    print(
        f"{result['scenario']}: {description} [{result['source']}], solver mode "
        f"{result['solver_mode']}, truth {result['truth']}"
        + (f", disturbed (seed {result['seed']})" if result["disturbed"] else "")
        + f", device {result['device']}"
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
    if side_by_side:
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
