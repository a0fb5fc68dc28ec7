"""Closed-loop maneuvers per second (``rvdjax bench --closed-loop``): one jitted maneuver at a
time against the batch engine, per scenario, batch and plant."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "FAMILY_SCENARIOS",
    "perturbed_states",
    "closed_loop_batch_benchmark",
    "format_closed_loop",
]


FAMILY_SCENARIOS = ("fastmpc-3d", "spot-2d-a", "rotating-target-b", "poseidyn-lqmpc", "thesis-vbar")


def perturbed_states(x0, n: int, seed: int = 0, rel: float = 0.02):
    """``n`` initial states: each non-zero component of ``x0`` perturbed uniformly by up to
    ``rel`` of its size (the first state is ``x0`` itself)."""
    x0 = jnp.asarray(x0, dtype=float)
    u = jax.random.uniform(jax.random.key(seed), (n, x0.shape[0]), minval=-1.0, maxval=1.0)
    x = x0 + rel * jnp.abs(x0) * u
    return x.at[0].set(x0)


def closed_loop_batch_benchmark(
    names=FAMILY_SCENARIOS,
    batches=(1, 16, 64, 256),
    runs: int = 256,
    single_runs: int = 16,
    disturbed: bool = False,
    mode: str = "accurate",
    chunk: int = 32,
    iterations: int = 3,
    progress=print,
    thrusters: bool = False,
    options=None,
) -> list[dict]:
    """Maneuvers per second flown one jitted maneuver at a time and by the batch engine.

    ``options``: the flight (:class:`~rvdjax.scenarios.flight.FlightOptions`; default: ``mode``
    and ``disturbed``, ideal forces); ``thrusters`` adds the thruster rows.

    ``thrusters``: fly every scenario twice in the same run, with ideal forces and with its
    thruster set (allocation, modulation, the truth under valve pulses); the rows say which
    (``plant``) and the thruster rows give their slowdown against the ideal-force row of the
    same scenario, method and batch (``slowdown``), also per MPC step (``slowdown_per_step``:
    a thruster maneuver may take more steps to dock).

    For each scenario, ``runs`` distinct initial states (:func:`perturbed_states`; with
    ``disturbed`` also distinct PRNG keys) are flown by the engine with B slots for every B in
    ``batches`` (after a compile on one tick), and the first ``single_runs`` of them one at a
    time through the jitted :func:`rvdjax.loop.fly` (after its compile). Rows: scenario,
    family, method, batch, runs, seconds, maneuvers_per_s, speedup over one at a time,
    peak_memory_mb (XLA's planned memory of the engine program: arguments, outputs and
    temporaries), docked_fraction, mean_iterations and the per-step iteration distribution.
    """
    from rvdjax.loop import fly
    from rvdjax.loop.engine import EngineConfig, arrays_source, compile_engine, run_batch
    from rvdjax.scenarios import FlightOptions, get_scenario

    if options is None:
        options = FlightOptions(mode=mode, disturbed=disturbed)
    mode, disturbed = options.mode, options.disturbed
    rows = []
    plants = ("ideal", "thrusters") if thrusters else ("ideal",)
    for name, plant in ((n, pl) for n in names for pl in plants):
        sc = get_scenario(name)
        flight = sc.flight(options.replace(thrusters=plant == "thrusters"))
        params, x0, loop, sp = flight.params, flight.x0, flight.loop, flight.solver_params
        x0s = perturbed_states(x0, runs)
        keys = jax.random.split(jax.random.key(1), runs)
        # one jitted maneuver at a time
        f = jax.jit(lambda p, x, k, s, lp=loop: fly(lp, p, x, k, s)[1])
        t0 = time.perf_counter()
        jax.block_until_ready(f(params, x0s[0], keys[0], sp))
        compile_s = time.perf_counter() - t0
        n1 = min(single_runs, runs)
        t0 = time.perf_counter()
        singles = [jax.block_until_ready(f(params, x0s[i], keys[i], sp)) for i in range(n1)]
        sec = time.perf_counter() - t0
        single_rate = n1 / sec
        docked = np.mean([bool(m.docked) for m in singles])
        its = np.mean([float(m.mean_iterations) for m in singles])
        steps = np.mean([int(m.steps) for m in singles])
        # the columns every row of this scenario and plant shares
        base = dict(scenario=name, family=sc.family, mode=mode, disturbed=disturbed, plant=plant)
        rows.append(
            dict(
                **base,
                method="one at a time (jitted fly)",
                batch=1,
                runs=n1,
                seconds=sec,
                maneuvers_per_s=single_rate,
                speedup=1.0,
                peak_memory_mb=float("nan"),
                compile_s=compile_s,
                docked_fraction=float(docked),
                mean_iterations=float(its),
                mean_steps=float(steps),
            )
        )
        progress(f"{name} ({plant}): one at a time {single_rate:.2f} maneuvers/s ({n1} runs)")
        for B in batches:
            cfg = EngineConfig(slots=B, chunk=chunk, iterations=iterations)
            source = arrays_source(x0s, keys)
            t0 = time.perf_counter()
            mem_mb = compile_engine(loop, source, params, sp, cfg)
            compile_s = time.perf_counter() - t0
            out = run_batch(loop, source, runs, params=params, solver_params=sp, config=cfg)
            m = out["metrics"]
            hist = np.asarray(m.iteration_histogram).sum(axis=0)
            rate = runs / out["seconds"]
            rows.append(
                dict(
                    **base,
                    method=f"engine (chunk {cfg.chunk_size}, {iterations} iterations / tick)",
                    batch=B,
                    runs=runs,
                    seconds=out["seconds"],
                    maneuvers_per_s=rate,
                    speedup=rate / single_rate,
                    peak_memory_mb=mem_mb,
                    compile_s=compile_s,
                    docked_fraction=float(np.mean(m.docked)),
                    mean_steps=float(np.mean(m.steps)),
                    mean_iterations=float(np.sum(hist * np.arange(len(hist))) / max(hist.sum(), 1)),
                    iterations_p50=_hist_quantile(hist, 0.5),
                    iterations_p90=_hist_quantile(hist, 0.9),
                    iterations_max=int(np.flatnonzero(hist)[-1]) if hist.any() else 0,
                    ticks=out["ticks"],
                )
            )
            progress(
                f"{name} ({plant}): B={B} {rate:.2f} maneuvers/s ({rate / single_rate:.1f}x), "
                f"{mem_mb:.0f} MB, docked {np.mean(m.docked):.2f}"
            )
    ideal = {(r["scenario"], r["method"], r["batch"]): r for r in rows if r["plant"] == "ideal"}
    for r in rows:
        ref = ideal.get((r["scenario"], r["method"], r["batch"]))
        r["slowdown"] = ref["maneuvers_per_s"] / r["maneuvers_per_s"] if ref else float("nan")
        r["slowdown_per_step"] = (
            r["slowdown"] * ref["mean_steps"] / r["mean_steps"] if ref else float("nan")
        )
    return rows


def _hist_quantile(hist, q: float) -> int:
    c = np.cumsum(hist)
    return int(np.searchsorted(c, q * c[-1])) if c[-1] else 0


def format_closed_loop(rows: list[dict]) -> str:
    head = (
        f"{'scenario':<20}{'plant':<10}{'method':<40}{'B':>5}{'runs':>6}{'man/s':>9}"
        f"{'x single':>9}{'slower':>8}{'/step':>7}{'mem MB':>8}{'docked':>8}{'its/step':>9}"
        f"{'p50/p90/max':>13}"
    )
    out = [head]
    for r in rows:
        dist = (
            f"{r['iterations_p50']}/{r['iterations_p90']}/{r['iterations_max']}"
            if "iterations_p50" in r
            else "-"
        )
        mem = "-" if np.isnan(r["peak_memory_mb"]) else f"{r['peak_memory_mb']:.0f}"
        slower = r.get("slowdown", float("nan"))
        per_step = r.get("slowdown_per_step", float("nan"))
        if r.get("plant", "ideal") == "ideal" or np.isnan(slower):
            slower = per_step = "-"
        else:
            slower, per_step = f"{slower:.2f}", f"{per_step:.2f}"
        out.append(
            f"{r['scenario']:<20}{r.get('plant', 'ideal'):<10}{r['method']:<40}{r['batch']:>5}"
            f"{r['runs']:>6}{r['maneuvers_per_s']:>9.2f}{r['speedup']:>9.1f}{slower:>8}"
            f"{per_step:>7}{mem:>8}"
            f"{r['docked_fraction']:>8.2f}{r['mean_iterations']:>9.2f}{dist:>13}"
        )
    return "\n".join(out)
