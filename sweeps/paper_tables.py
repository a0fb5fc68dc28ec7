"""Every scenario in both solver modes: the tables of docs/reproduction.md.

Flies every registered scenario once in accurate mode and once in paper mode (one jitted
maneuver each, one XLA thread as ``rvdjax run``), prints two Markdown tables (the figures
next to the papers' published values; paper mode next to accurate mode) and writes every
run's metrics to ``paper_tables.json`` (or the path given as the argument).

    python sweeps/paper_tables.py [out.json]
"""

from __future__ import annotations

import json
import sys


def main(out: str = "paper_tables.json") -> int:
    from rvdjax.outputs import check_file
    from rvdjax.xla_options import one_thread

    check_file(out, "out", (".json",))
    one_thread()

    from rvdjax.loop.metrics import metrics_row
    from rvdjax.scenarios import SCENARIOS, FlightOptions

    results = {}
    for name in SCENARIOS:
        for mode in ("accurate", "paper"):
            _, m, ms = SCENARIOS[name].flight(FlightOptions(mode=mode)).fly_timed()
            results[f"{name}/{mode}"] = {**metrics_row(m), "ms_per_step": ms}
            print(f"{name} {mode}: docked {bool(m.docked)}", file=sys.stderr, flush=True)
    from rvdjax.provenance import benchmark_block

    with open(out, "w") as f:
        prov = benchmark_block("sweeps/paper_tables.py", {"out": str(out)})
        json.dump({**results, "provenance": prov}, f, indent=1)

    def effort(name, r):
        fam = SCENARIOS[name].family
        if fam == "three-phase":
            return f"{r['delta_v_m_s']:.2f} m/s"
        if fam == "rendezvous":
            return f"{r['effort_l1_N_s'] / 1e3:.2f} kN s"
        return f"{r['effort_l1_N_s']:.3g} N s"

    print("| scenario | docked | time to dock | effort | published | violation | statuses |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, sc in SCENARIOS.items():
        r = results[f"{name}/accurate"]
        pub = "; ".join(
            f"{k.split('_')[0]} {label} {v:g}"
            for k, refs in sc.published.items()
            for label, v in refs.items()
        )
        counts = "/".join(str(c) for c in r["solver_status_counts"].values())
        t = r["time_to_dock_s"]
        print(
            f"| `{name}` | {r['docked']} | {t:.1f} s | {effort(name, r)} | {pub or '-'} | "
            f"{r['max_violation_m']:.1g} m | {counts} |"
        )
    print()
    print("| scenario | paper mode: docked, time, effort | accurate mode | converged / max-iter |")
    print("| --- | --- | --- | --- |")
    for name in SCENARIOS:
        p, a = results[f"{name}/paper"], results[f"{name}/accurate"]
        c = p["solver_status_counts"]
        print(
            f"| `{name}` | {p['docked']}, {p['time_to_dock_s']:.1f} s, {effort(name, p)} | "
            f"{a['time_to_dock_s']:.1f} s, {effort(name, a)} | "
            f"{c['converged']} / {c['max_iter']} |"
        )
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
