"""Cost of one solver iteration as the batch engine runs it: a chunk of C started slots of a
scenario (accurate mode, the model shared by the chunk when the family has one), three
vmapped iterations per call, timed after a compile. Prints microseconds per problem and
iteration (best and median of five timings of 20 calls). With ``--phases``, the three phases
of an engine tick per slot instead: the OCP build and solver start of a new MPC step, the
three iterations, and the finish, plant step and metrics of a solved step. With
``--unbatched``, the cost of an iteration of one problem without ``vmap`` against the same
problem's share of a chunk, each from the difference of 30 and 3 iterations per call (so the
call's own overhead, ~80-95 us for one problem, cancels): the most that batching can save per
iteration on this machine.

Usage (one core; results in docs/benchmark.md)::

    taskset -c 0 python sweeps/engine_iteration.py --scenarios fastmpc-3d,thesis-vbar --chunk 1,32
    taskset -c 0 python sweeps/engine_iteration.py --phases --scenarios fastmpc-3d
    taskset -c 0 python sweeps/engine_iteration.py --unbatched
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np
from jax import lax

from rvdjax.bench import perturbed_states
from rvdjax.loop.engine.slots import _strip_model, _with_model, model_of
from rvdjax.loop.kernel import Prepared, advance, init, metrics, prepare
from rvdjax.scenarios import FlightOptions, get_scenario
from rvdjax.solver.driver import finish, iterate, start

ITERATIONS = 3


def _chunk(name: str, chunk: int, n_iterations: int = ITERATIONS, unbatched: bool = False):
    """The phases of an engine tick for a chunk of C slots of a scenario (accurate mode, the
    model shared by the chunk as the engine shares it, when the family has one), jitted and
    vmapped over the chunk, and C started slots to time them on."""
    sc = get_scenario(name)
    flight = sc.flight(FlightOptions(mode="accurate"))
    params, x0, loop = flight.params, flight.x0, flight.loop
    sp = sc.solver_params("accurate")
    settings = loop.config.settings

    def with_model(ocp, g):
        return _with_model(ocp, model_of(loop, params, g))

    @jax.jit
    def prepare_start(states):
        def one(st):
            nxt = prepare(loop, params, st)
            model = model_of(loop, params, nxt.guidance)
            ocp, solve = start(nxt.ocp, settings, sp, nxt.warm, trusted_model=model is not None)
            return nxt, _strip_model(ocp, model), solve

        return jax.vmap(one)(states)

    @jax.jit
    def iterations(ocps, gs, solves):
        def one(ocp, g, s):
            ocp = with_model(ocp, g)
            return lax.fori_loop(0, n_iterations, lambda _, st: iterate(ocp, settings, sp, st), s)

        if unbatched:  # the first problem alone, no batch axis
            return one(*jax.tree.map(lambda a: a[0], (ocps, gs, solves)))
        return jax.vmap(one)(ocps, gs, solves)

    @jax.jit
    def step_done(states, nxts, ocps, solves):
        def one(st, nxt, ocp, s):
            ocp = with_model(ocp, nxt.guidance)
            sol = finish(ocp, settings, sp, s)
            new, _ = advance(
                loop, params, sp, st, Prepared(nxt.guidance, ocp, nxt.hard, None, nxt.nav), sol
            )
            return new, metrics(loop, params, new)

        return jax.vmap(one)(states, nxts, ocps, solves)

    x0s = perturbed_states(x0, chunk)
    keys = jax.random.split(jax.random.key(1), chunk)
    states = jax.jit(jax.vmap(lambda x, k: init(loop, params, x, k)))(x0s, keys)
    return states, prepare_start, iterations, step_done


def _timings_us(fn, args, per, repeats=20) -> list[float]:
    """Five timings of ``repeats`` calls (after one untimed call), microseconds per ``per``."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(fn(*args))
        times.append((time.perf_counter() - t0) / repeats / per * 1e6)
    return times


def iteration_cost(name: str, chunk: int) -> dict:
    states, prepare_start, iterations, _ = _chunk(name, chunk)
    nxts, ocps, solves = prepare_start(states)
    t0 = time.perf_counter()
    compiled = iterations.lower(ocps, nxts.guidance, solves).compile()
    compile_s = time.perf_counter() - t0
    per = _timings_us(compiled, (ocps, nxts.guidance, solves), ITERATIONS * chunk)
    return dict(
        scenario=name,
        chunk=chunk,
        best_us=min(per),
        median_us=float(np.median(per)),
        compile_s=compile_s,
    )


def unbatched_cost(name: str, chunk: int) -> dict:
    """Microseconds per problem and iteration, one problem without vmap against a chunk of
    ``chunk``: (time of 30 iterations - time of 3) / 27 per call, so the call's overhead
    cancels."""
    out = dict(scenario=name, chunk=chunk)
    for key, c, unb in (("unbatched_us", 1, True), ("chunk_us", chunk, False)):
        t = {}
        for k in (3, 30):
            states, prepare_start, iterations, _ = _chunk(name, c, n_iterations=k, unbatched=unb)
            nxts, ocps, solves = prepare_start(states)
            args = (ocps, nxts.guidance, solves)
            t[k] = min(_timings_us(iterations, args, 1, repeats=20 if k == 3 else 5))
        out[key] = (t[30] - t[3]) / 27 / c
        if unb:
            out["call_overhead_us"] = t[3] - 3 * out[key]
    out["ratio"] = out["unbatched_us"] / out["chunk_us"]
    return out


def phase_costs(name: str, chunk: int) -> dict:
    """Microseconds per slot of each phase of an engine tick, for a chunk of slots."""
    states, prepare_start, iterations, step_done = _chunk(name, chunk)
    nxts, ocps, solves = prepare_start(states)
    solves = iterations(ocps, nxts.guidance, solves)
    return dict(
        scenario=name,
        chunk=chunk,
        prepare_start_us=min(_timings_us(prepare_start, (states,), chunk)),
        iterations_us=min(_timings_us(iterations, (ocps, nxts.guidance, solves), chunk)),
        step_done_us=min(_timings_us(step_done, (states, nxts, ocps, solves), chunk)),
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--scenarios", default="fastmpc-3d,spot-2d-a,rotating-target-b,poseidyn-lqmpc,thesis-vbar"
    )
    ap.add_argument("--chunk", default="32")
    ap.add_argument("--phases", action="store_true", help="time the phases of a tick instead")
    ap.add_argument(
        "--unbatched", action="store_true", help="one problem without vmap against a chunk"
    )
    args = ap.parse_args(argv)
    # (measure, columns: (header, key, format)) of the chosen table
    if args.unbatched:
        measure, columns = (
            unbatched_cost,
            [
                ("unbatched us", "unbatched_us", ">14.2f"),
                ("chunk", "chunk", ">7"),
                ("us / problem", "chunk_us", ">14.2f"),
                ("ratio", "ratio", ">7.2f"),
                ("call overhead us", "call_overhead_us", ">18.0f"),
            ],
        )
    elif args.phases:
        measure, columns = (
            phase_costs,
            [
                ("chunk", "chunk", ">6"),
                ("prepare+start", "prepare_start_us", ">15.1f"),
                (f"{ITERATIONS} iterations", "iterations_us", ">14.1f"),
                ("finish+advance", "step_done_us", ">16.1f"),
            ],
        )
    else:
        measure, columns = (
            iteration_cost,
            [
                ("chunk", "chunk", ">6"),
                ("us best", "best_us", ">10.2f"),
                ("us median", "median_us", ">11.2f"),
                ("compile s", "compile_s", ">11.1f"),
            ],
        )
    # a header takes its column's width: the digits between ">" and "." of the format
    print(f"{'scenario':<20}" + "".join(f"{h:>{f[1:].split('.')[0]}}" for h, _, f in columns))
    for name in args.scenarios.split(","):
        for c in (int(v) for v in args.chunk.split(",")):
            r = measure(name, c)
            print(f"{name:<20}" + "".join(f"{r[k]:{f}}" for _, k, f in columns))


if __name__ == "__main__":
    main()
