"""Issue 9's benchmark: tune thesis-vbar (paper 003) and poseidyn-lqmpc (paper 001, from its
initial weights) against the hand tuning and a random search with the same budget, judged on
held-out maneuvers, with a trade-off curve over the loss's time weight; and the cost of one
gradient step over 64 full maneuvers against the forward batch, with peak memory.

    python sweeps/tuning_benchmark.py tune [--out DIR] [--scenarios a,b]
    python sweeps/tuning_benchmark.py cost [--out DIR]

Each tuning writes its directory (tuned_params.json, tables, plots) under DIR. ``cost`` runs
every configuration in a fresh process, so each peak memory figure is its own.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import rvdjax  # noqa: F401  (float64)
from rvdjax.tune import TuneSpec, parse_loss, tune

CASES = {
    "poseidyn-lqmpc": dict(params=("Q", "R", "terminal_scale"), train=16, heldout=64, steps=40),
    "thesis-vbar": dict(params=("Q", "R"), train=16, heldout=64, steps=20, n_steps=120),
}
TIME_WEIGHTS = (0.25, 0.5, 2.0, 4.0)  # the trade-off curve (1.0 is the main run)
COST_CASES = (("thesis-vbar", 120), ("thesis-vbar", 300), ("poseidyn-lqmpc", None))


def _f(v, fmt):
    return "-" if v is None else format(v, fmt)


def _row(label, m):
    return (
        f"| {label} | {_f(m['effort'], '.4g')} | {_f(m['time_to_dock_s'], '.1f')} | "
        f"{m['docked_fraction']:.2f} | {m['max_violation_m']:.3g} | {_f(m.get('loss'), '.4f')} |"
    )


# "No constraint violation" in the judgement: the truth's largest violation of a hard row at
# most 1 mm (soft rows with an exact penalty leave micrometres; 50x below paper 003's 5 cm
# navigation noise). The tables print the measured violation.
VIOLATION_TOL_M = 1e-3


def _dominates(m, hand) -> bool:
    return (
        m["docked_fraction"] >= hand["docked_fraction"]
        and m["max_violation_m"] <= max(hand["max_violation_m"], VIOLATION_TOL_M)
        and m["effort"] < hand["effort"]
        and m["time_to_dock_s"] <= hand["time_to_dock_s"]
    )


def cmd_tune(out: Path, scenarios) -> None:
    results = {}
    for name in scenarios:
        base = TuneSpec(scenario=name, **CASES[name])
        main = tune(base, out=out / name, progress=True)
        hand = main["heldout"]["hand"]
        curve = [{"label": "time=1", **main["heldout"]["tuned"]}]
        for w in TIME_WEIGHTS:
            spec = dataclasses.replace(base, loss=parse_loss(f"time={w:g}"), random_search=False)
            r = tune(spec, out=out / f"{name}-time{w:g}", progress=True)
            curve.append({"label": f"time={w:g}", **r["heldout"]["tuned"]})
        results[name] = {"main": main, "curve": curve}
        print(
            f"\n{name}: tuned {','.join(main['params'])} ({main['n_values']} values), "
            f"{main['train']} training maneuvers, {main['steps']} steps, effort = "
            f"{hand['effort_metric']}, {main['heldout_runs']} held-out maneuvers"
        )
        print(
            "| tuning (loss time weight 1) | effort | time to dock [s] | docked | "
            "max violation [m] | held-out loss |"
        )
        print("| --- | --- | --- | --- | --- | --- |")
        for label, m in main["heldout"].items():
            print(_row(label, m))
        print(
            "\n| trade-off point | effort | time to dock [s] | docked | max violation [m] | "
            "dominates hand |"
        )
        print("| --- | --- | --- | --- | --- | --- |")
        for p in curve:
            print(f"{_row(p['label'], p).rsplit('|', 2)[0]}| {_dominates(p, hand)} |")
        print(
            f"train loss {main['train_loss']}; gradient step {_f(main['grad_step_s'], '.3g')} s, "
            f"forward {main['forward_s']:.3g} s, wall {main['wall_s']:.0f} s",
            flush=True,
        )
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            from rvdjax.tune.figures import plot_tradeoff

            fig, ax = plt.subplots(figsize=(5, 4))
            plot_tradeoff(ax, curve, {"label": "hand", **hand})
            ax.set_title(f"{name}: held-out trade-off")
            fig.tight_layout()
            fig.savefig(out / f"{name}-tradeoff.png", dpi=120)
            plt.close(fig)
        except ImportError:
            pass
    from rvdjax.provenance import benchmark_block

    options = {"out": str(out), "scenarios": list(scenarios)}
    prov = benchmark_block("sweeps/tuning_benchmark.py tune", options)
    (out / "tune.json").write_text(json.dumps({**results, "provenance": prov}, indent=2))


def cmd_cost_one(name: str, n_steps, remat: bool) -> dict:
    spec = TuneSpec(
        scenario=name,
        params=("Q", "R"),
        train=64,
        heldout=1,
        steps=3,
        n_steps=n_steps,
        random_search=False,
        remat=remat,
    )
    r = tune(spec, out=None, progress=False)
    return {
        k: r[k]
        for k in (
            "scenario",
            "n_steps",
            "forward_s",
            "grad_step_s",
            "grad_to_forward",
            "peak_memory_mb",
            "remat",
        )
    }


def cmd_cost(out: Path) -> None:
    rows = []
    for name, n_steps in COST_CASES:
        for remat in (True, False):
            cmd = [sys.executable, __file__, "cost-one", "--case", f"{name},{n_steps},{int(remat)}"]
            res = subprocess.run(cmd, capture_output=True, text=True, check=True)
            rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
            print(rows[-1], flush=True)
    print(
        "| scenario | jax.checkpoint | MPC steps | forward, 64 maneuvers [s] | "
        "gradient step [s] | ratio | peak RSS [MB] |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(
            f"| {r['scenario']} | {r['remat']} | {r['n_steps']} | {r['forward_s']:.2f} | "
            f"{r['grad_step_s']:.2f} | {r['grad_to_forward']:.2f} | {r['peak_memory_mb']:.0f} |"
        )
    from rvdjax.provenance import benchmark_block

    prov = benchmark_block("sweeps/tuning_benchmark.py cost", {"out": str(out)})
    (out / "cost.json").write_text(json.dumps({"provenance": prov, "rows": rows}, indent=2))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("tune", "cost", "cost-one"))
    ap.add_argument("--out", default="tuning-benchmark")
    ap.add_argument("--scenarios", default=",".join(CASES))
    ap.add_argument("--case", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.what == "cost-one":
        name, n_steps, remat = a.case.split(",")
        r = cmd_cost_one(name, None if n_steps == "None" else int(n_steps), remat == "1")
        print(json.dumps(r))
        return 0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    if a.what == "tune":
        cmd_tune(out, a.scenarios.split(","))
    else:
        cmd_cost(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
