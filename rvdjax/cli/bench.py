"""``rvdjax bench``: QP solves against Clarabel and the peers, or closed-loop maneuvers per
second (``--closed-loop``); the flight options apply to the closed loop."""

from __future__ import annotations

import json
import sys

from rvdjax.cli.options import add_flight_options, add_json, flight_options, ints

__all__ = ["add_parser", "cmd"]


def add_parser(sub) -> None:
    p = sub.add_parser(
        "bench",
        help="benchmark: QP solves against Clarabel and the peers, or closed-loop maneuvers "
        "per second in batches (--closed-loop)",
    )
    add_json(p, "print the rows as JSON")
    add_flight_options(
        p,
        help={
            "thrusters": "closed loop: fly every scenario with ideal forces and with its "
            "thrusters in the same run (slowdown column)",
            "seed": "closed loop: unused (the runs' keys are fixed, distinct per run)",
        },
    )
    p.add_argument("--out", metavar="FILE", help="also write the rows to FILE (.json)")
    p.add_argument("--quick", action="store_true", help="small batches (a smoke run)")
    p.add_argument(
        "--closed-loop",
        action="store_true",
        help="whole maneuvers: one jitted maneuver at a time against the batch engine",
    )
    p.add_argument(
        "--batch", type=ints, help="batch sizes (QP: vmapped batches; closed loop: slots)"
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
    p.add_argument("--chunk", type=int, default=32, help="closed loop: slots per vmapped chunk")
    p.add_argument(
        "--iterations", type=int, default=3, help="closed loop: solver iterations per slot per tick"
    )
    p.add_argument("--horizons", type=ints, help="QP: horizons for the scaling rows, e.g. 15,30")
    p.add_argument("--peers", help="QP: comma-separated peers (default: all installed)")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="CPU threads for XLA and the peers (default 1, as in the README)",
    )
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    from rvdjax.bench import machine_info
    from rvdjax.outputs import check_file

    check_file(args.out, "--out", (".json",))
    if args.peers is not None and not args.closed_loop:
        from rvdjax.peers import PEERS

        for name in args.peers.split(","):
            if name and name not in PEERS:
                raise ValueError(f"--peers: {name!r} is not a peer; choose from {', '.join(PEERS)}")

    def progress(msg):
        print(msg, file=sys.stderr, flush=True)

    if args.closed_loop:
        from rvdjax.bench import FAMILY_SCENARIOS, closed_loop_batch_benchmark, format_closed_loop
        from rvdjax.scenarios import get_scenario

        names = args.scenarios.split(",") if args.scenarios else FAMILY_SCENARIOS
        options = flight_options(args, thrusters=False)
        for n in names:
            get_scenario(n).thruster_set(args.thrusters)  # refused before anything flies
        rows = closed_loop_batch_benchmark(
            names,
            batches=tuple(args.batch or (1, 16, 64, 256)),
            runs=args.runs,
            single_runs=args.single_runs,
            options=options,
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
            from rvdjax.provenance import benchmark_block

            prov = benchmark_block("rvdjax bench", vars(args), device=args.device_used)
            doc = {"machine": machine_info(), "provenance": prov, "rows": rows}
            json.dump(doc, f, indent=1)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        print(f"machine: {machine_info()}")
        print(text)
    return 0
