"""A dual warm start for the accurate mode, measured (not adopted): iterations per MPC step
when the primal-dual solve starts from the previous step's multipliers, shifted one stage,
instead of the central point at kappa0 (rvdjax.solver.pd_algebra.pd_start).

Each MPC step of one maneuver (the published x0, accurate mode) is solved twice from the same
primal warm start: as rvdjax does, and with the multipliers lam, mu, pi of the previous
step's solution shifted one stage, raised where needed so that every complementarity product
is at least delta = ``--deltas`` x the default start's mean complementarity (the soft rows'
slacks set for that delta). The maneuver itself flies the default solve's answer, so both
starts see the same OCPs.

    python sweeps/dual_warm_start.py [--scenario thesis-vbar] [--deltas 1e-1,1e-2,1e-3]
"""

from __future__ import annotations

import argparse

import numpy as np

import rvdjax  # noqa: F401  (float64)


def main(argv=None) -> None:
    import jax
    import jax.numpy as jnp
    from jax import lax

    from rvdjax.loop.kernel import advance, init, prepare
    from rvdjax.scenarios import FlightOptions, get_scenario
    from rvdjax.solver.barrier import m_eff, rows_in, soft_slack
    from rvdjax.solver.driver import finish, finished, iterate, start

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="thesis-vbar")
    ap.add_argument("--deltas", default="1e-1,1e-2,1e-3")
    args = ap.parse_args(argv)
    deltas = [float(d) for d in args.deltas.split(",")]
    sc = get_scenario(args.scenario)
    flight = sc.flight(FlightOptions(mode="accurate"))
    params, x0, loop = flight.params, flight.x0, flight.loop
    sp = sc.solver_params("accurate")
    settings = loop.config.settings

    def shift(a):
        return jnp.concatenate([a[1:], a[-1:]], axis=0)

    def iterate_all(ocp, s):
        return lax.while_loop(
            lambda s: ~finished(settings, s), lambda s: iterate(ocp, settings, sp, s), s
        )

    @jax.jit
    def default(state):
        prep = prepare(loop, params, state)
        ocp, s = start(prep.ocp, settings, sp, prep.warm)
        return prep, ocp, iterate_all(ocp, s)

    @jax.jit
    def dual_warm(state, prev, delta_rel):
        prep = prepare(loop, params, state)
        ocp, s = start(prep.ocp, settings, sp, prep.warm)
        c, rows = s.core, rows_in(ocp)
        delta = delta_rel * c.gap / jnp.maximum(m_eff(rows), 1.0)
        s_new, sx = soft_slack(c.g, rows.rho, delta)
        lam = jnp.maximum(shift(prev.lam), delta / c.su)
        mu = jnp.maximum(shift(prev.mu), delta / sx)
        pi = jnp.maximum(shift(prev.pi), delta / s_new)
        gap = jnp.sum(rows.wu * c.su * lam) + jnp.sum(rows.wx * (sx * mu + s_new * pi))
        core = c._replace(s=s_new, lam=lam, mu=mu, pi=pi, gap=gap)
        return iterate_all(ocp, s._replace(core=core))

    @jax.jit
    def fly_on(state, prep, ocp, s):
        return advance(loop, params, sp, state, prep, finish(ocp, settings, sp, s))[0]

    state = init(loop, params, x0, jax.random.key(0))
    base, warm = [], {d: [] for d in deltas}
    du = dict.fromkeys(deltas, 0.0)
    prev = None
    for _ in range(loop.config.n_steps):
        if not bool(state.active):
            break
        prep, ocp, s = default(state)
        if prev is not None:
            base.append(int(s.core.it))
            scale = float(jnp.max(jnp.abs(s.core.u))) + 1e-12
            for d in deltas:
                w = dual_warm(state, prev, d)
                warm[d].append(int(w.core.it))
                du[d] = max(du[d], float(jnp.max(jnp.abs(w.core.u - s.core.u))) / scale)
        prev = s.core
        state = fly_on(state, prep, ocp, s)

    def stats(v):
        v = np.asarray(v)
        return f"{v.mean():6.2f} (p90 {np.percentile(v, 90):3.0f}, max {v.max():3d})"

    print(f"{args.scenario}: {len(base) + 1} MPC steps; iterations per step from the 2nd step")
    print(f"  default start (central point at kappa0)      {stats(base)}")
    for d in deltas:
        print(
            f"  shifted multipliers, delta = {d:<8g} x kappa0 {stats(warm[d])}  largest input "
            f"difference {du[d]:.1e} of the largest input"
        )


if __name__ == "__main__":
    main()
