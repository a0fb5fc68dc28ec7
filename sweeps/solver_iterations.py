"""Solver iterations per MPC step over one maneuver of each scenario (docs/benchmark.md).

Flies every scenario (accurate mode, CW truth, the published initial state) with the jitted
``rvdjax.loop.fly`` and prints the mean, p90 and largest number of solver iterations per MPC
step, the solver statuses over the steps and the maneuver's delta-v and time to dock (so that a
solver change that lowers the iterations can be seen not to change the answers). With
``--disturbed K`` the disturbed rows fly K PRNG keys of ``thesis-vbar`` (with the navigation
filter) and ``rotating-target-b``. With ``--vary NAME=V1,V2,...`` each scenario flies once
per value of a solver parameter instead, its delta-v and applied inputs compared with the
first value's.

    python sweeps/solver_iterations.py [--scenarios a,b,...] [--disturbed 8] [--json]
    python sweeps/solver_iterations.py --scenarios thesis-vbar,fastmpc-3d --vary tol=1e-9,1e-6
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

import rvdjax  # noqa: F401  (float64)
from rvdjax.loop import kernel
from rvdjax.scenarios import SCENARIOS, FlightOptions, get_scenario

DISTURBED = (("thesis-vbar", True), ("rotating-target-b", False))


def _row(name, infos, m, runs):
    active = np.asarray(infos.active)
    its = np.asarray(infos.iterations)[active]
    return {
        "scenario": name,
        "runs": runs,
        "iterations_mean": float(its.mean()),
        "iterations_p90": float(np.percentile(its, 90)),
        "iterations_max": int(its.max()),
        "status_counts": np.asarray(m.status_counts).reshape(-1, 4).sum(0).tolist(),
        "docked": int(np.asarray(m.docked).sum()),
        "delta_v_m_s": float(np.mean(np.asarray(m.delta_v_m_s))),
        "time_to_dock_s": float(np.mean(np.asarray(m.time_to_dock_s))),
    }


def nominal(name: str, setting: tuple[str, float] | None = None) -> dict:
    sc = get_scenario(name)
    flight = sc.flight(FlightOptions(mode="accurate"))
    params, x0, loop = flight.params, flight.x0, flight.loop
    sp = sc.solver_params("accurate")
    if setting is not None:
        sp = sp._replace(**{setting[0]: jnp.asarray(setting[1])})
    infos, m = jax.jit(lambda p, sp: kernel.fly(loop, p, jnp.asarray(x0), None, sp))(params, sp)
    label = name if setting is None else f"{name}, {setting[0]} {setting[1]:g}"
    row = _row(label, infos, m, 1)
    if setting is not None:  # the applied inputs, compared across settings
        row["u"] = np.asarray(infos.u)[np.asarray(infos.active)]
    return row


def disturbed(name: str, nav_filter: bool, runs: int) -> dict:
    sc = get_scenario(name)
    flight = sc.flight(FlightOptions(mode="accurate", disturbed=True, nav_filter=nav_filter))
    params, x0, loop = flight.params, flight.x0, flight.loop
    keys = jax.random.split(jax.random.PRNGKey(0), runs)
    f = jax.jit(jax.vmap(lambda k: kernel.fly(loop, params, jnp.asarray(x0), k)))
    infos, m = f(keys)
    label = f"{name}, disturbed" + (", navigation filter" if nav_filter else "")
    return _row(label, infos, m, runs)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated names")
    ap.add_argument("--disturbed", type=int, default=8, help="PRNG keys per disturbed row")
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument(
        "--vary",
        metavar="NAME=V1,V2,...",
        help="a solver parameter (rvdjax.solver.SolverParams field, e.g. tol or kappa0_rel): "
        "nominal rows per value, with the delta-v and the applied inputs compared with the "
        "first value's",
    )
    args = ap.parse_args(argv)
    names = [n for n in args.scenarios.split(",") if n]
    for n in names:
        get_scenario(n)  # unknown names fail before anything compiles
    if args.vary:
        field, _, values = args.vary.partition("=")
        values = [float(v) for v in values.split(",")]
        for n in names:
            base = nominal(n, (field, values[0]))
            for v in values:
                r = nominal(n, (field, v))
                du = np.max(np.abs(r["u"] - base["u"])) / np.max(np.abs(base["u"]))
                ddv = abs(r["delta_v_m_s"] - base["delta_v_m_s"]) / base["delta_v_m_s"]
                print(
                    f"{r['scenario']:<36} iterations/step {r['iterations_mean']:6.2f} (p90 "
                    f"{r['iterations_p90']:3.0f})  dv {r['delta_v_m_s']:.9f} m/s (rel. change "
                    f"{ddv:.1e})  max |u - u_first| / max |u_first| {du:.1e}"
                )
        return
    rows = [nominal(n) for n in names]
    if args.disturbed > 0:
        rows += [disturbed(n, nav, args.disturbed) for n, nav in DISTURBED]
    for r in rows:
        if args.json:
            print(json.dumps(r))
        else:
            print(
                f"{r['scenario']:<48} runs {r['runs']:>3}  iterations/step "
                f"{r['iterations_mean']:6.2f} (p90 {r['iterations_p90']:3.0f}, max "
                f"{r['iterations_max']:3d})  statuses {r['status_counts']}  docked "
                f"{r['docked']}/{r['runs']}  dv {r['delta_v_m_s']:.6f} m/s  "
                f"t {r['time_to_dock_s']:.1f} s"
            )


if __name__ == "__main__":
    main()
