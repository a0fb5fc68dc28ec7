"""Papers 001 and 002 against their own numbers: the sweeps behind docs/reproduction.md.

Every maneuver flies its thrusters (``FlightOptions(thrusters=True)``) through the batch
engine; each sweep writes one CSV row per run as the runs finish and resumes where it stopped
(the rows already in the file are not flown again).

``paper002``: rotating-target-a/b/c with the port's initial angle phi0 in {0, 45, .., 315}
deg and both senses of rotation (paper 002 publishes neither), under each allocation of the
thrusters ("least-thrust": force and torque together; "separate": a pure force by pairs plus
a pure couple). Per run: Eq. 11's effort (every thruster's impulse) split by phase (free
flight, final approach), the time in each phase, soft-infeasible steps and the truth's
margins.

``paper001``: poseidyn-lqmpc and -retuned with navigation noise (sigma_v in {0, 1, 2, 4, 8}
mm/s, sigma_p in {1, 5} mm, no thrust error, 4 seeds), the docking distance (0.05, 0.1, 0.16,
0.2 m) and the preview ((Ts, N) in {(5 s, 20), (1 s, 20), (5 s, 4)}).

``report``: the tables of docs/reproduction.md from the CSVs.

    python sweeps/reproduction_sweeps.py paper002 --out sweeps-out/
    python sweeps/reproduction_sweeps.py paper001 --out sweeps-out/
    python sweeps/reproduction_sweeps.py report --out sweeps-out/
"""

from __future__ import annotations

import argparse
import csv
import itertools
import os
import time

import jax
import numpy as np

from rvdjax.loop.engine import EngineConfig, arrays_source, run_batch
from rvdjax.scenarios import SCENARIOS, FlightOptions

CASES = ("a", "b", "c")
PHI0_DEG = tuple(range(0, 360, 45))
SENSES = (1, -1)
ALLOCATIONS = ("least-thrust", "separate")
# paper 002 Table 2 and the arithmetic of its gamma = 0.9 experiment (Table 3): the approach
# lasts about 57 s, so the free flight about 95 / 98.5 / 108.5 s in cases A / B / C
PAPER002 = {"a": (5.98, 152.0), "b": (7.04, 155.0), "c": (9.40, 165.0)}
FREE_FLIGHT_S = {"a": 95.0, "b": 98.5, "c": 108.5}

NOISE_V = (0.0, 1e-3, 2e-3, 4e-3, 8e-3)
NOISE_P = (1e-3, 5e-3)
SEEDS = 4
DOCK_TOL = (0.05, 0.1, 0.16, 0.2)
PREVIEW = ((5.0, 20), (1.0, 20), (5.0, 4))
PAPER001 = {"poseidyn-lqmpc": (5.3, 102.8), "poseidyn-lqmpc-retuned": (5.0, 142.8)}
NO_THRUST_ERROR = dict(eta_w=0.0, eta_v=0.0, w0_sigma=0.0)


def _done(path: str, key_fields) -> set:
    if not os.path.exists(path) or os.path.getsize(path) == 0:
        return set()
    with open(path, newline="") as f:
        return {tuple(row[k] for k in key_fields) for row in csv.DictReader(f)}


def _fly(path: str, items, key_fields, loop, metric_row, slots=64):
    """Fly ``items`` ((key dict, params, x0, seed)) not yet in ``path``; append rows as they
    finish."""
    done = _done(path, key_fields)
    todo = [it for it in items if tuple(str(it[0][k]) for k in key_fields) not in done]
    if not todo:
        print(f"{path}: all {len(items)} runs already there")
        return
    params = jax.tree.map(lambda *a: np.stack(a), *[it[1] for it in todo])
    x0 = np.stack([it[2] for it in todo])
    keys = jax.vmap(jax.random.key)(np.asarray([it[3] for it in todo]))
    new = not os.path.exists(path) or os.path.getsize(path) == 0
    f = open(path, "a", newline="")
    writer = None

    def on_results(idx, m):
        nonlocal writer
        for j, i in enumerate(idx):
            row = {**todo[i][0], **metric_row(jax.tree.map(lambda a, j=j: a[j], m))}
            if writer is None:
                writer = csv.DictWriter(f, fieldnames=list(row))
                if new:
                    writer.writeheader()
            writer.writerow(row)
        f.flush()

    t0 = time.perf_counter()
    run_batch(
        loop,
        arrays_source(x0, keys=keys, params=params),
        len(todo),
        config=EngineConfig(slots=min(slots, len(todo)), chunk=min(32, len(todo))),
        on_results=on_results,
        progress=lambda d, n: print(f"  {d}/{n} runs", flush=True),
    )
    f.close()
    print(f"{path}: {len(todo)} runs in {time.perf_counter() - t0:.1f} s")


def _common(m) -> dict:
    counts = np.asarray(m.status_counts)
    return dict(
        docked=bool(m.docked),
        time_s=float(m.time_to_dock_s),
        effort_l1_N_s=float(m.effort_l1_N_s),
        thruster_impulse_N_s=float(m.thruster_impulse_N_s),
        max_violation_m=float(m.max_violation_m),
        infeasible_steps=int(counts[2]),
        steps=int(m.steps),
        **{f"margin_{k}_m": float(v) for k, v in m.margins_m.items()},
    )


def paper002(out: str) -> int:
    for alloc in ALLOCATIONS:
        items = []
        for case, phi, sense in itertools.product(CASES, PHI0_DEG, SENSES):
            sc = SCENARIOS[f"rotating-target-{case}"]
            rate = sc.physical["target_rate_deg_s"]
            tset = sc.thrusters.replace(allocation=alloc)
            flight = sc.flight(
                FlightOptions(thrusters=tset, n_steps=250),
                check=False,
                target=(2.0, 2.0, float(np.deg2rad(phi))),
                target_rate_deg_s=sense * rate,
            )
            key = dict(case=case, phi0_deg=phi, sense=sense, allocation=alloc)
            items.append((key, flight.params, flight.x0, 0))
        sc = SCENARIOS["rotating-target-a"]
        tset = sc.thrusters.replace(allocation=alloc)
        loop = sc.flight(FlightOptions(thrusters=tset, n_steps=250), check=False).loop

        def row(m):
            out_ = _common(m)
            for ph, name in enumerate(("free", "approach")):
                out_[f"{name}_effort_N_s"] = float(m.phase_thruster_impulse_N_s[ph])
                out_[f"{name}_time_s"] = float(m.phase_time_s[ph])
            return out_

        _fly(
            os.path.join(out, "paper002_geometry.csv"),
            items,
            ("case", "phi0_deg", "sense", "allocation"),
            loop,
            row,
        )
    return 0


def paper001(out: str) -> int:
    for ts, N in PREVIEW:
        items = []
        for name, sv, sp, tol, seed in itertools.product(
            PAPER001, NOISE_V, NOISE_P, DOCK_TOL, range(SEEDS)
        ):
            if sv == 0.0 and seed > 0:
                continue  # no noise: one run per setting is the answer
            sc = SCENARIOS[name]
            dist = dict(sigma_pos=sp, sigma_vel=sv, **NO_THRUST_ERROR)
            flight = sc.flight(
                FlightOptions(thrusters=True, disturbed=True),
                check=False,
                ts=ts,
                dock_tol=tol,
                disturbances=dist,
            )
            key = dict(
                scenario=name, ts_s=ts, N=N, sigma_v=sv, sigma_p=sp, dock_tol_m=tol, seed=seed
            )
            items.append((key, flight.params, flight.x0, seed))
        sc = SCENARIOS["poseidyn-lqmpc"]
        n_steps = int(round(sc.n_steps * 5.0 / ts))
        options = FlightOptions(thrusters=True, disturbed=True, n_steps=n_steps)
        loop = sc.flight(options, config=dict(N=N), check=False).loop
        _fly(
            os.path.join(out, "paper001_noise_preview.csv"),
            items,
            ("scenario", "ts_s", "N", "sigma_v", "sigma_p", "dock_tol_m", "seed"),
            loop,
            _common,
        )
    return 0


VARIANTS = {
    "ideal": dict(thrusters=False),
    "thrusters": dict(thrusters=True),
    # the thesis' own formulation with its thrusters: the impulsive model (Eq. 3.1) while the
    # burns last up to 5 s from each period's start
    "thrusters-impulsive-model": dict(
        thrusters=True, config=dict(finite_burn=False), family="three-phase"
    ),
    # paper 001's solver: the dual method of its ref. 38, capped at 100 iterations
    "thrusters-dual": dict(thrusters=True, mode="dual", family="poseidyn"),
    "ideal-dual": dict(thrusters=False, mode="dual", family="poseidyn"),
}


def table(out: str) -> int:
    """Every scenario with published figures, with ideal forces and with its thrusters (one
    maneuver each, accurate mode, linear truth); one row per (scenario, variant)."""
    from rvdjax.loop import fly

    path = os.path.join(out, "reproduction_table.csv")
    done = _done(path, ("scenario", "variant"))
    names = [n for n, sc in SCENARIOS.items() if sc.published and sc.thrusters is not None]
    new = not os.path.exists(path) or os.path.getsize(path) == 0
    with open(path, "a", newline="") as f:
        writer = None
        for name in names:
            sc = SCENARIOS[name]
            for variant, v in VARIANTS.items():
                if (name, variant) in done:
                    continue
                if v.get("family", sc.family) != sc.family:
                    continue
                settings = None
                if v.get("mode") == "dual":
                    from rvdjax.solver import SolverSettings

                    settings = SolverSettings(mode="dual", max_iter=100)
                flight = sc.flight(
                    FlightOptions(thrusters=v["thrusters"]),
                    settings=settings,
                    config=v.get("config", {}),
                    check=False,
                )
                params, x0, loop = flight.params, flight.x0, flight.loop
                t0 = time.perf_counter()
                _, m = jax.jit(lambda p, x, lp=loop: fly(lp, p, x))(params, x0)
                m = jax.tree.map(np.asarray, m)
                row = dict(scenario=name, variant=variant, **_common(m))
                for key, refs in sc.published.items():
                    metric = sc.thruster_metrics.get(key, key) if v["thrusters"] else key
                    val = float(getattr(m, metric))
                    ref = next(iter(refs.values()))
                    row[f"{key}"] = val
                    row[f"{key}_metric"] = metric
                    row[f"{key}_paper"] = ref
                    row[f"{key}_gap"] = val / ref - 1.0
                row["delta_v_m_s"] = float(m.delta_v_m_s)
                row["seconds"] = time.perf_counter() - t0
                if writer is None:
                    fields = sorted(
                        set(row) | {f"{k}{s}" for k in ("effort_l1_N_s", "delta_v_m_s",
                                                          "time_to_dock_s")
                                    for s in ("", "_metric", "_paper", "_gap")}
                        | {f"margin_{b}_m" for b in ("keep_out", "overshoot", "docking_cone",
                                                       "speed", "entry_cone", "obstacles",
                                                       "target_keep_out", "keep_out_plane")}
                    )  # fmt: skip
                    writer = csv.DictWriter(f, fieldnames=fields, restval="")
                    if new:
                        writer.writeheader()
                writer.writerow(row)
                f.flush()
                print(f"{name} {variant}: {row['seconds']:.0f} s", flush=True)
    return 0


def _read(path):
    import pandas as pd

    return pd.read_csv(path)


def report(out: str) -> int:
    import pandas as pd

    path = os.path.join(out, "paper002_geometry.csv")
    if os.path.exists(path):
        df = _read(path)
        print("paper 002: every geometry (effort = Eq. 11 [N s]; time [s]; free flight [s])")
        for (alloc, phi, sense), g in df.groupby(["allocation", "phi0_deg", "sense"]):
            g = g.set_index("case")
            if set(g.index) != set(CASES):
                continue
            e = {c: g.loc[c, "thruster_impulse_N_s"] for c in CASES}
            t = {c: g.loc[c, "time_s"] for c in CASES}
            ff = {c: g.loc[c, "free_time_s"] for c in CASES}
            inf = int(g["infeasible_steps"].sum())
            cone = float(g["margin_entry_cone_m"].min())
            viol = float(g["max_violation_m"].max())
            keep = abs(ff["a"] - FREE_FLIGHT_S["a"]) <= 15 and 0 <= ff["c"] - ff["a"] <= 30
            print(
                f"{alloc:<13} phi0 {phi:>3} sense {sense:+d}  "
                + "  ".join(f"{c.upper()} {e[c]:.2f}/{t[c]:.0f} ({ff[c]:.0f})" for c in CASES)
                + f"  C/A {e['c'] / e['a']:.2f}  infeasible {inf}  cone {cone:+.3f}"
                f"  viol {viol:.4f}{'  KEPT' if keep else ''}"
            )
    path = os.path.join(out, "reproduction_table.csv")
    if os.path.exists(path):
        df = _read(path)
        print("published versus reproduced (gap of each figure; violation [m])")
        counted = {}
        for (name, variant), g in df.groupby(["scenario", "variant"], sort=False):
            r = g.iloc[-1]
            gaps = {
                k: r[f"{k}_gap"]
                for k in ("effort_l1_N_s", "delta_v_m_s", "time_to_dock_s")
                if f"{k}_gap" in r and pd.notna(r[f"{k}_gap"])
            }
            within = all(abs(v) <= 0.15 for v in gaps.values())
            safe = r["max_violation_m"] <= 0.01
            ok = bool(r["docked"]) and within and safe
            counted.setdefault(variant, []).append(ok)
            figs = "  ".join(
                f"{r[k]:.4g} vs {r[k + '_paper']:.4g} ({100 * v:+.1f} %)" for k, v in gaps.items()
            )
            print(
                f"{name:<26}{variant:<27}{figs}  viol {r['max_violation_m']:.4f}"
                f"{'  COUNTED' if ok else ''}"
            )
        for variant, oks in counted.items():
            print(f"{variant}: {sum(oks)} of {len(oks)} within 15 % on every figure and safe")

    path = os.path.join(out, "paper001_noise_preview.csv")
    if os.path.exists(path):
        df = _read(path)
        keys = ["scenario", "ts_s", "N", "sigma_v", "sigma_p", "dock_tol_m"]
        agg = (
            df.groupby(keys)
            .agg(
                effort=("effort_l1_N_s", "mean"),
                time=("time_s", "mean"),
                docked=("docked", "mean"),
                viol=("max_violation_m", "max"),
            )
            .reset_index()
        )
        print("\npaper 001: mean over seeds (effort = Eq. 14 [N s]; time [s])")
        settings = ["ts_s", "N", "sigma_v", "sigma_p", "dock_tol_m"]
        rows = []
        for s, g in agg.groupby(settings):
            g = g.set_index("scenario")
            if set(g.index) != set(PAPER001):
                continue
            gaps = []
            for name, (e_pub, t_pub) in PAPER001.items():
                gaps += [g.loc[name, "effort"] / e_pub - 1, g.loc[name, "time"] / t_pub - 1]
            rows.append((max(abs(x) for x in gaps), s, g, gaps))
        rows.sort(key=lambda r: r[0])
        for worst, s, g, _gaps in rows[:15]:
            label = ", ".join(f"{k}={v:g}" for k, v in zip(settings, s, strict=True))
            figs = "  ".join(
                f"{n.split('-')[-1]} {g.loc[n, 'effort']:.2f} N s / {g.loc[n, 'time']:.1f} s"
                for n in PAPER001
            )
            print(f"worst gap {100 * worst:5.1f} %  {label}:  {figs}")
        _ = pd
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("paper002", "paper001", "table", "report"))
    ap.add_argument("--out", required=True, help="directory of the CSVs (created)")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    whats = {"paper002": paper002, "paper001": paper001, "table": table, "report": report}
    return whats[args.what](args.out)


if __name__ == "__main__":
    raise SystemExit(main())
