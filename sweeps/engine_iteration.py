"""Cost of one solver iteration as the batch engine runs it: a chunk of C started slots of a
scenario (accurate mode, the model shared by the chunk when the family has one), three
vmapped iterations per call, timed after a compile. Prints microseconds per problem and
iteration (best and median of five timings of 20 calls).

Usage (one core; results in docs/benchmark.md)::

    taskset -c 0 python sweeps/engine_iteration.py --scenarios fastmpc-3d,thesis-vbar --chunk 1,32
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np
from jax import lax

from rvdjax.bench import perturbed_states
from rvdjax.loop.engine import _strip_model, _with_model
from rvdjax.loop.kernel import init, prepare
from rvdjax.scenarios import get_scenario
from rvdjax.solver.driver import iterate, start

ITERATIONS = 3


def iteration_cost(name: str, chunk: int, repeats: int = 20) -> dict:
    sc = get_scenario(name)
    params, x0 = sc.build()
    loop = sc.loop("accurate")
    sp = sc.solver_params("accurate")
    settings = loop.config.settings
    # families with a model share it across the chunk, as the engine does
    shared = loop.family.model is not None
    model = loop.family.model(params, loop.config.family) if shared else None
    x0s = perturbed_states(x0, chunk)
    keys = jax.random.split(jax.random.key(1), chunk)

    @jax.jit
    def started(x0s, keys):
        def one(x, k):
            nxt = prepare(loop, params, init(loop, params, x, k))
            ocp, solve = start(nxt.ocp, settings, sp, nxt.warm, trusted_model=shared)
            return (_strip_model(loop, ocp) if shared else ocp), solve

        return jax.vmap(one)(x0s, keys)

    @jax.jit
    def run(ocps, solves):
        def one(ocp, s):
            ocp = _with_model(loop, ocp, model) if shared else ocp
            return lax.fori_loop(0, ITERATIONS, lambda _, st: iterate(ocp, st, settings, sp), s)

        return jax.vmap(one)(ocps, solves)

    ocps, solves = started(x0s, keys)
    t0 = time.perf_counter()
    compiled = run.lower(ocps, solves).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(ocps, solves))
    per = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(compiled(ocps, solves))
        per.append((time.perf_counter() - t0) / repeats / ITERATIONS / chunk * 1e6)
    return dict(
        scenario=name,
        chunk=chunk,
        best_us=min(per),
        median_us=float(np.median(per)),
        compile_s=compile_s,
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--scenarios", default="fastmpc-3d,spot-2d-a,rotating-target-b,poseidyn-lqmpc,thesis-vbar"
    )
    ap.add_argument("--chunk", default="32")
    args = ap.parse_args(argv)
    print(f"{'scenario':<20}{'chunk':>6}{'us best':>10}{'us median':>11}{'compile s':>11}")
    for name in args.scenarios.split(","):
        for c in (int(v) for v in args.chunk.split(",")):
            r = iteration_cost(name, c)
            print(
                f"{name:<20}{c:>6}{r['best_us']:>10.2f}{r['median_us']:>11.2f}{r['compile_s']:>11.1f}"
            )


if __name__ == "__main__":
    main()
