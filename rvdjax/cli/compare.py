"""``rvdjax compare``: one scenario flown by every solver (paper 000 Sec. IV)."""

from __future__ import annotations

import json
import sys

from rvdjax.cli.options import add_flight_options, add_json, add_scenario, flight_options

__all__ = ["add_parser", "cmd"]


def add_parser(sub) -> None:
    p = sub.add_parser("compare", help="fly a scenario with every solver (paper 000 Sec. IV)")
    add_scenario(p, default="fastmpc-3d")
    add_flight_options(
        p,
        fixed=("mode",),  # every solver variant flies its own mode
        help={
            "thrusters": "the rvdjax, Clarabel and HPIPM loops fly the vehicle's thrusters (the "
            "NMPC and IDVD baselines keep ideal forces)"
        },
    )
    add_json(p)
    p.add_argument("--no-nmpc", action="store_true", help="skip the CasADi/IPOPT baselines")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    from rvdjax.compare import compare_solvers, format_comparison
    from rvdjax.scenarios import get_scenario

    sc = get_scenario(args.scenario)
    options = flight_options(args)
    sc.thruster_set(options.thrusters)  # refused before anything flies

    def progress(msg):
        print(msg, file=sys.stderr, flush=True)

    rows = compare_solvers(args.scenario, progress=progress, nmpc=not args.no_nmpc, options=options)
    if args.json:
        out = {"scenario": sc.name, "device": args.device_used, "published": sc.published}
        print(json.dumps({**out, "rows": rows}, indent=2))
    else:
        print(format_comparison(sc.name, rows, sc.published))
        print(f"device: {args.device_used}")
        print(
            "ms/step: wall time of the closed loop per MPC step (Clarabel, HPIPM: host "
            "callback with the QP assembly); NMPC row: IPOPT calls only; IDVD row: per IPOPT "
            "(re-)plan, incl. the simulation"
        )
    return 0
