"""Solver iterations per MPC step over one maneuver of each scenario (docs/benchmark.md).

Flies every scenario (accurate mode, CW truth, the published initial state) with the jitted
``rvdjax.loop.fly`` and prints the mean, p90 and largest number of solver iterations per MPC
step, the solver statuses over the steps and the maneuver's delta-v and time to dock (so that a
solver change that lowers the iterations can be seen not to change the answers). With
``--disturbed K`` the disturbed rows fly K PRNG keys of ``thesis-vbar`` (with the navigation
filter) and ``rotating-target-b``. With ``--vary NAME=V1,V2,...`` each scenario flies once
per value of a solver parameter instead, its delta-v and applied inputs compared with the
first value's. With ``--peers clarabel,piqp`` each scenario flies its maneuver one MPC step
at a time and every step's QP (the OCP rvdjax solved, soft rows as their exact penalty) is
solved again from a cold start by rvdjax and by each peer: their iterations per MPC step
beside rvdjax's warm-started ones, on the same QPs.

    python sweeps/solver_iterations.py [--scenarios a,b,...] [--disturbed 8] [--json]
    python sweeps/solver_iterations.py --scenarios thesis-vbar,fastmpc-3d --vary tol=1e-9,1e-6
    python sweeps/solver_iterations.py --scenarios thesis-vbar,fastmpc-3d --peers clarabel,piqp
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


def _stats(v) -> str:
    v = np.asarray(v)
    return f"{v.mean():6.2f} (p90 {np.percentile(v, 90):3.0f}, max {v.max():3d})"


def against_peers(name: str, peers: list[str]) -> dict:
    """One maneuver flown a step at a time (as ``kernel.fly`` flies it): rvdjax's iterations
    per MPC step, warm-started as it flies and cold, and each peer's on the same step's QP,
    cold, with the peer's failures counted."""
    from jax import lax

    from rvdjax.loop.kernel import advance, init, prepare
    from rvdjax.solver import solve
    from rvdjax.solver.clarabel import solve_clarabel_backend
    from rvdjax.solver.driver import finish, finished, iterate, start
    from rvdjax.solver.types import Status

    sc = get_scenario(name)
    flight = sc.flight(FlightOptions(mode="accurate"))
    params, loop = flight.params, flight.loop
    sp = sc.solver_params("accurate")
    settings = loop.config.settings

    @jax.jit
    def step(state):
        prep = prepare(loop, params, state)
        ocp, s = start(prep.ocp, settings, sp, prep.warm)
        s = lax.while_loop(
            lambda s: ~finished(settings, s), lambda s: iterate(ocp, settings, sp, s), s
        )
        return prep, ocp, s

    @jax.jit
    def fly_on(state, prep, ocp, s):
        return advance(loop, params, sp, state, prep, finish(ocp, settings, sp, s))[0]

    @jax.jit
    def cold(ocp):
        return solve(ocp, settings, sp).iterations

    state = init(loop, params, jnp.asarray(flight.x0), jax.random.key(0))
    its = {"rvdjax": [], "rvdjax, cold": [], **{p: [] for p in peers}}
    failed = dict.fromkeys(peers, 0)
    for _ in range(loop.config.n_steps):
        if not bool(state.active):
            break
        prep, ocp, s = step(state)
        its["rvdjax"].append(int(s.core.it))
        its["rvdjax, cold"].append(int(cold(ocp)))
        for p in peers:
            sol = solve_clarabel_backend(ocp, p)
            its[p].append(int(sol.iterations))
            failed[p] += int(sol.status) not in (Status.CONVERGED, Status.INFEASIBLE)
        state = fly_on(state, prep, ocp, s)
    return {"scenario": name, "steps": len(its["rvdjax"]), "iterations": its, "failed": failed}


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
    ap.add_argument(
        "--peers",
        metavar="NAME,...",
        help="solve every MPC step's QP again with these peers, cold (those installed of "
        "clarabel, piqp, daqp, daqp-condensed, osqp, hpipm, qpax), and print their iterations per "
        "step beside rvdjax's",
    )
    args = ap.parse_args(argv)
    names = [n for n in args.scenarios.split(",") if n]
    for n in names:
        get_scenario(n)  # unknown names fail before anything compiles
    if args.peers:
        from rvdjax.peers import available_peers

        peers = [p for p in args.peers.split(",") if p]
        for p in peers:
            if p not in available_peers():
                ap.exit(2, f"--peers: {p!r} is not one of {', '.join(available_peers())}\n")
        for n in names:
            r = against_peers(n, peers)
            print(f"{n:<26} {r['steps']:4d} MPC steps, iterations per step:")
            for solver, v in r["iterations"].items():
                note = f"  failed {r['failed'][solver]}" if solver in r["failed"] else ""
                start = {"rvdjax": " (warm)", "rvdjax, cold": ""}.get(solver, " (cold)")
                print(f"    {solver + start:<20} {_stats(v)}{note}")
        return
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
