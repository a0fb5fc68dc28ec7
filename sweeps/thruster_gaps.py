"""The papers' figures with thrusters, and the unpublished values that set the remaining gaps.

``tables``: every published scenario flown with ideal forces and with its thruster set (one
maneuver each, accurate mode, linear truth): the effort as each paper defines it, time to
dock, thruster impulse, valve openings, dropped pulses and the largest truth violation, next
to the paper's figures.

``sweeps``: the values the papers do not publish, swept together where they interact
(effort depends on the time to dock), with the thrusters on, through the batch engine (one
compile per scenario family, every run with its own parameters):

* paper 002 (rotating-target-a/b/c): the phase-switch thresholds c_alpha1 (``c_pos``) and
  c_alpha2 (``c_att_deg``), the docked tolerance (``dock_tol``) and the thrust per thruster;
* paper 001 (poseidyn-lqmpc, -retuned): the docking condition (``dock_tol``,
  ``dock_speed_tol``), the keep-out hyperplane's rotation rate and the thrust per thruster.

For each case it prints the settings that bring effort and time within 15 % of the paper (if
any), the closest setting on each figure alone, and whether one setting closes both.

    python sweeps/thruster_gaps.py tables
    python sweeps/thruster_gaps.py sweeps [--out thruster_gaps.csv]
"""

from __future__ import annotations

import argparse
import csv
import itertools
import time

import jax
import numpy as np

from rvdjax.loop import fly
from rvdjax.loop.engine import EngineConfig, arrays_source, run_batch
from rvdjax.scenarios import SCENARIOS, FlightOptions

PUBLISHED = [n for n, sc in SCENARIOS.items() if sc.published and sc.thrusters is not None]

SWEEPS = {
    "planar-docking": dict(
        scenarios=("rotating-target-a", "rotating-target-b", "rotating-target-c"),
        grid=dict(
            c_pos=(0.02, 0.05, 0.1),
            c_att_deg=(2.0, 5.0, 10.0),
            dock_tol=(0.01, 0.02, 0.05),
            thruster_thrust_N=(0.15, 0.3),
        ),
        n_steps=250,
    ),
    "poseidyn": dict(
        scenarios=("poseidyn-lqmpc", "poseidyn-lqmpc-retuned"),
        grid=dict(
            dock_tol=(0.01, 0.02, 0.05),
            dock_speed_tol=(0.005, 0.01, 0.05),
            plane_rate_deg_s=(0.9, 1.8, 3.6),
            thruster_thrust_N=(0.15, 0.3),
        ),
        n_steps=100,
    ),
}


def _paper_figure(sc, key: str, m, i=None):
    """The figure ``key`` as the paper defines it with the thrusters flying."""
    name = sc.thruster_metrics.get(key, key)
    v = getattr(m, name)
    return float(v if i is None else v[i]), name


def tables() -> int:
    print(
        f"{'scenario':<26}{'figure':<34}{'paper':>9}{'ideal':>10}{'thrusters':>11}"
        f"{'gap':>8}  {'openings':>8}{'dropped':>8}{'viol [m]':>10}"
    )
    for name in PUBLISHED:
        sc = SCENARIOS[name]
        out = {}
        for on in (False, True):
            flight = sc.flight(FlightOptions(thrusters=on), check=False)
            params, x0, loop = flight.params, flight.x0, flight.loop
            _, m = jax.jit(lambda p, x, lp=loop: fly(lp, p, x))(params, x0)
            out[on] = jax.tree.map(np.asarray, m)
        for key, refs in sc.published.items():
            ideal = float(getattr(out[False], key))
            thr, metric = _paper_figure(sc, key, out[True])
            for label, ref in refs.items():
                print(
                    f"{name:<26}{metric + ' / ' + label:<34}{ref:>9.4g}{ideal:>10.4g}"
                    f"{thr:>11.4g}{100 * (thr / ref - 1):>7.1f}%  "
                    f"{int(out[True].valve_openings):>8}{int(out[True].pulses_dropped):>8}"
                    f"{float(out[True].max_violation_m):>10.3g}"
                )
    return 0


def sweeps(out_csv: str | None) -> int:
    rows = []
    for fam, cfg in SWEEPS.items():
        names, keys = cfg["scenarios"], list(cfg["grid"])
        combos = list(itertools.product(*cfg["grid"].values()))
        options = FlightOptions(thrusters=True, n_steps=cfg["n_steps"])
        built, labels = [], []
        for name in names:
            for combo in combos:
                values = dict(zip(keys, combo, strict=True))
                built.append(SCENARIOS[name].flight(options, check=False, **values))
                labels.append((name, combo))
        params = jax.tree.map(lambda *a: np.stack(a), *[b.params for b in built])
        x0 = np.stack([b.x0 for b in built])
        loop = SCENARIOS[names[0]].flight(options, check=False).loop
        t0 = time.perf_counter()
        res = run_batch(
            loop,
            arrays_source(x0, params=params),
            len(built),
            config=EngineConfig(slots=64, chunk=32),
        )
        m = jax.tree.map(np.asarray, res["metrics"])
        print(f"{fam}: {len(built)} maneuvers in {time.perf_counter() - t0:.1f} s")
        for i, (name, combo) in enumerate(labels):
            sc = SCENARIOS[name]
            row = dict(scenario=name, **dict(zip(keys, combo, strict=True)))
            row["docked"] = bool(m.docked[i])
            row["max_violation_m"] = float(m.max_violation_m[i])
            for key, refs in sc.published.items():
                v, metric = _paper_figure(sc, key, m, i)
                ref = next(iter(refs.values()))  # the simulation figure (first label)
                row[key] = v
                row[f"{key}_metric"] = metric
                row[f"{key}_gap"] = v / ref - 1.0
            rows.append(row)
        for name in names:
            mine = [r for r in rows if r["scenario"] == name and r["docked"]]
            e_key, t_key = "effort_l1_N_s", "time_to_dock_s"
            both = [
                r for r in mine if abs(r[f"{e_key}_gap"]) <= 0.15 and abs(r[f"{t_key}_gap"]) <= 0.15
            ]
            best_e = min(mine, key=lambda r: abs(r[f"{e_key}_gap"]))
            best_t = min(mine, key=lambda r: abs(r[f"{t_key}_gap"]))
            best_sum = min(mine, key=lambda r: abs(r[f"{e_key}_gap"]) + abs(r[f"{t_key}_gap"]))

            def show(r, keys=keys, e_key=e_key, t_key=t_key):
                vals = ", ".join(f"{k}={r[k]:g}" for k in keys)
                return (
                    f"{vals}: effort {r[e_key]:.3g} ({100 * r[e_key + '_gap']:+.0f} %), "
                    f"time {r[t_key]:.4g} s ({100 * r[t_key + '_gap']:+.0f} %)"
                )

            print(f"  {name}: {len(mine)}/{len(combos)} docked")
            print(f"    closest effort: {show(best_e)}")
            print(f"    closest time:   {show(best_t)}")
            print(f"    closest both:   {show(best_sum)}")
            print(
                f"    settings with both within 15 %: {len(both)}"
                + (f" (e.g. {show(both[0])})" if both else "")
            )
    if out_csv:
        with open(out_csv, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=sorted({k for r in rows for k in r}))
            w.writeheader()
            w.writerows(rows)
        print(f"rows written to {out_csv}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("tables", "sweeps"))
    ap.add_argument("--out", help="sweeps: write one row per run to this CSV")
    args = ap.parse_args()
    if args.out:
        from rvdjax.outputs import check_file

        check_file(args.out, "--out", (".csv",))
    return tables() if args.what == "tables" else sweeps(args.out)


if __name__ == "__main__":
    raise SystemExit(main())
