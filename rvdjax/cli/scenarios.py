"""``rvdjax list`` and ``rvdjax scenario show``: the scenarios, and a scenario as a file."""

from __future__ import annotations

import sys

from rvdjax.cli.options import add_scenario

__all__ = ["add_parser"]


def add_parser(sub) -> None:
    p = sub.add_parser("list", help="list the named scenarios")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("scenario", help="show a scenario; write it as a file to edit and fly")
    q = p.add_subparsers(dest="scenario_command", required=True).add_parser(
        "show", help="a scenario's values, or its scenario file (--toml, --out)"
    )
    add_scenario(q)
    q.add_argument("--toml", action="store_true", help="print the scenario file (TOML)")
    q.add_argument("--out", metavar="FILE", help="write the scenario file to FILE (.toml)")
    q.set_defaults(func=cmd_scenario)


def cmd_list(args) -> int:
    """``rvdjax list``: the named scenarios."""
    from rvdjax.scenarios import DEFAULT_SCENARIO, SCENARIOS

    width = max(len(name) for name in SCENARIOS) + 2
    for name, sc in SCENARIOS.items():
        mark = " (default)" if name == DEFAULT_SCENARIO else ""
        print(f"{name:<{width}}{sc.description}  [{sc.source}; family {sc.family}]{mark}")
    return 0


def cmd_scenario(args) -> int:
    """``rvdjax scenario show NAME``: a scenario's summary, or its scenario file (``--toml``
    prints it, ``--out FILE`` writes it)."""
    from rvdjax.outputs import check_file
    from rvdjax.scenarios import get_scenario
    from rvdjax.scenarios.files import scenario_summary, scenario_to_toml

    check_file(args.out, "--out", (".toml",))
    sc = get_scenario(args.scenario)
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
