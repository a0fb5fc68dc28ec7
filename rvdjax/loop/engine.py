"""The batch engine: many closed-loop runs through a fixed set of slots.

B slots step together; a queue of runs (a function of the run index) feeds them. Every *tick*
each slot does a fixed amount of work:

1. if its solve has finished (stopping test, failure or iteration cap): the second half of
   the MPC step (:func:`rvdjax.loop.kernel.advance`: command, actuator, plant, guidance,
   accumulation); a run that ends (docked, out of steps, failed) writes its metrics to the
   result ring and frees the slot;
2. a free slot takes the next run from the queue (auto-reset, as vectorised simulators do);
3. a slot that needs a new solve prepares it (:func:`rvdjax.loop.kernel.prepare` and the
   solver's ``start``);
4. ``iterations`` solver iterations (:func:`rvdjax.solver.iterate`; a finished iterate is
   frozen).

So a slot never waits for the slowest member of the batch: a solve that needs more iterations
simply continues on the next tick, and a slot whose run ended takes the next run. Slots are
processed in chunks (``chunk`` slots per ``vmap``, a loop over chunks) so that a chunk's working
set stays in cache; a chunk whose slots are all free is skipped (a real branch, not a masked
one), and when the queue is empty the live slots are packed into the first chunks.

Results do not depend on the number of slots, the chunking or the order in which runs finish:
a run's computation depends only on its own inputs (its parameters, initial state and PRNG
key), and the solver's iterate is frozen once finished, however the iterations were grouped.

Results are collected on the host between *segments* of ticks (:func:`run_batch`), so a long
study can write them as it goes; the device keeps only the slots and a ring of R finished
results (memory set by the slots, not by the number of runs).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from rvdjax.loop.kernel import (
    Loop,
    LoopState,
    Metrics,
    Prepared,
    advance,
    init,
    metrics,
    prepare,
)
from rvdjax.ocp import OCP
from rvdjax.solver import SolverParams, SolveState, finish, finished, iterate, start
from rvdjax.solver.driver import MODEL_FIELDS

__all__ = [
    "RunInputs",
    "Source",
    "EngineConfig",
    "run_batch",
    "fly_batch",
    "arrays_source",
    "compile_engine",
]


class RunInputs(NamedTuple):
    """What the queue gives for one run index.

    Attributes:
        x0: (nx,) initial state.
        key: the run's PRNG key (disturbances).
        params: the run's family parameters, or None for the engine's shared parameters.
        solver: the run's :class:`SolverParams`, or None for the shared ones.
    """

    x0: jnp.ndarray
    key: jnp.ndarray
    params: Any = None
    solver: SolverParams | None = None


@dataclasses.dataclass(frozen=True)
class EngineConfig:
    """Static engine configuration.

    Attributes:
        slots: B, runs in flight at once.
        chunk: slots per vmapped chunk (cache-sized; B is rounded up to a multiple).
        iterations: solver iterations per slot per tick.
        ticks_per_segment: ticks between two collections of results on the host.
        ring: finished results kept on the device between collections (>= slots).
        devices: the slots are sharded over this many devices (the first ``devices`` of
            ``jax.local_devices()``; a ``Mesh`` with one axis): each device flies
            ``ceil(slots / devices)`` slots and every ``devices``-th run of the queue, with no
            communication between devices.
    """

    slots: int = 256
    chunk: int = 32
    iterations: int = 3
    ticks_per_segment: int = 256
    ring: int = 0  # 0: 4 * slots
    devices: int = 1

    def __post_init__(self):
        for name in ("slots", "chunk", "iterations", "ticks_per_segment", "devices"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")

    @property
    def per_device(self) -> EngineConfig:
        """The configuration of one device's share of the slots."""
        if self.devices == 1:
            return self
        return dataclasses.replace(self, slots=math.ceil(self.slots / self.devices), devices=1)

    @property
    def chunk_size(self) -> int:
        return min(self.chunk, self.slots)

    @property
    def n_chunks(self) -> int:
        return math.ceil(self.slots / self.chunk_size)

    @property
    def n_slots(self) -> int:
        return self.n_chunks * self.chunk_size

    @property
    def ring_size(self) -> int:
        return self.ring if self.ring else 4 * self.n_slots


class Slot(NamedTuple):
    """One slot: its run, the loop state, the prepared step and the solve in progress."""

    run: jnp.ndarray  # () run index (-1: free)
    live: jnp.ndarray  # () a run is in progress
    state: LoopState
    guidance: Any  # the observed guidance state of the current step
    ocp: OCP  # the (sanitised) OCP of the current step; without its model (A, B, c, Q, R:
    #           empty placeholders) when the family rebuilds it from the parameters
    hard: jnp.ndarray  # (N, m) hard rows of the current step
    solve: SolveState
    params: Any  # the run's parameters (None when shared)
    solver: Any  # the run's solver parameters (None when shared)
    nav: Any  # the navigation filter's estimate after this step's update (None: no filter)


class EngineState(NamedTuple):
    slots: Slot  # leading axis n_slots
    next_run: jnp.ndarray  # () next run index to hand out
    n_runs: jnp.ndarray  # () runs in the queue
    ring_run: jnp.ndarray  # (R,) run index held by each ring entry (-1: free)
    ring_done: jnp.ndarray  # (R,) the entry holds a finished result
    ring: Metrics  # (R, ...) finished results
    ticks: jnp.ndarray  # () ticks so far
    stalled: jnp.ndarray  # () a free slot could not take a run (ring full): collect


class Source(NamedTuple):
    """A queue of runs: ``fn(data, i) -> RunInputs`` for run index i (a traced int). ``fn`` is
    static (hashable: a module-level function), ``data`` a pytree of arrays passed to the
    compiled program, so a new queue of the same shapes does not recompile."""

    fn: Callable
    data: Any


def _pick_arrays(data, i):
    x0s, keys, params, solver = data
    pick = lambda tree: jax.tree.map(lambda a: a[i], tree)  # noqa: E731
    return RunInputs(
        x0=x0s[i],
        key=keys[i],
        params=None if params is None else pick(params),
        solver=None if solver is None else pick(solver),
    )


def arrays_source(x0s, keys=None, params=None, solver=None) -> Source:
    """A queue from arrays with a leading run axis: ``x0s`` (n, nx), ``keys`` (n,) (default
    ``jax.random.split(key(0), n)``), ``params`` / ``solver`` pytrees with a leading run axis
    (or None: the engine's shared ones)."""
    x0s = jnp.asarray(x0s)
    n = x0s.shape[0]
    keys = jax.random.split(jax.random.key(0), n) if keys is None else keys
    as_jax = lambda tree: None if tree is None else jax.tree.map(jnp.asarray, tree)  # noqa: E731
    return Source(_pick_arrays, (x0s, keys, as_jax(params), as_jax(solver)))


def _where(c, a, b):
    return jax.tree.map(lambda x, y: jnp.where(c, x, y), a, b)


def _strip_model(loop: Loop, ocp: OCP) -> OCP:
    """The OCP without the model a family rebuilds from its parameters (stored per slot)."""
    if loop.family.model is None:
        return ocp
    return ocp._replace(**{k: jnp.zeros((), ocp.B.dtype) for k in MODEL_FIELDS})


def _with_model(loop: Loop, ocp: OCP, model) -> OCP:
    if loop.family.model is None:
        return ocp
    return ocp._replace(**dict(zip(MODEL_FIELDS, model, strict=True)))


def _empty_slot(loop: Loop, params, sp, source, per_run_params, per_run_solver) -> Slot:
    """A free slot with the right shapes (built from run 0, then marked free)."""
    run = source(jnp.asarray(0))
    p = run.params if per_run_params else params
    s = run.solver if per_run_solver else sp
    state = init(loop, p, run.x0, run.key)
    prep = prepare(loop, p, state)
    ocp, solve_state = start(
        prep.ocp, loop.config.settings, s, prep.warm, trusted_model=loop.family.model is not None
    )
    ocp = _strip_model(loop, ocp)
    solve_state = solve_state._replace(core=solve_state.core._replace(done=jnp.asarray(True)))
    return Slot(
        run=jnp.asarray(-1, jnp.int32),
        live=jnp.asarray(False),
        state=state._replace(active=jnp.asarray(False)),
        guidance=prep.guidance,
        ocp=ocp,
        hard=prep.hard,
        solve=solve_state,
        params=p if per_run_params else None,
        solver=s if per_run_solver else None,
        nav=prep.nav,
    )


def _chunk_tick(
    loop, cfg: EngineConfig, shared_params, shared_sp, source, slots: Slot, assign, idx
):
    """One tick of a chunk of slots (module docstring); returns (slots, ended, run, metrics).

    Each phase is vmapped over the chunk; the phases that only some slots need (a new run, a
    new solve) are skipped for the whole chunk when no slot needs them (a real branch)."""
    settings = loop.config.settings
    fam = loop.family
    per_run_params = slots.params is not None
    per_run_solver = slots.solver is not None
    trusted = fam.model is not None
    # the model shared by the chunk (unbatched: one large product per stage for all slots)
    shared_model = (
        fam.model(shared_params, loop.config.family) if trusted and not per_run_params else None
    )

    def params_of(slot):
        return (slot.params if per_run_params else shared_params), (
            slot.solver if per_run_solver else shared_sp
        )

    def ocp_of(slot, params):
        if not trusted:
            return slot.ocp
        model = shared_model if shared_model is not None else fam.model(params, loop.config.family)
        return _with_model(loop, slot.ocp, model)

    # 1. the MPC step whose solve has finished
    def step_done(slot):
        params, sp = params_of(slot)
        solved = slot.live & finished(slot.solve, settings)
        ocp = ocp_of(slot, params)
        sol = finish(ocp, slot.solve, settings, sp)
        prep = Prepared(slot.guidance, ocp, slot.hard, None, slot.nav)
        stepped, _ = advance(loop, params, sp, slot.state, prep, sol)
        state = _where(solved, stepped, slot.state)
        ended = solved & ~state.active
        return slot._replace(state=state, live=slot.live & ~ended), solved, ended

    old_run = slots.run
    slots, solved, ended = jax.vmap(step_done)(slots)

    result = jax.vmap(lambda s: metrics(loop, params_of(s)[0], s.state))(slots)

    # 2. a new run for a free slot
    def load(slot, a, i):
        run = source(i)
        params = run.params if per_run_params else shared_params
        fresh = init(loop, params, run.x0, run.key)
        slot = slot._replace(
            run=jnp.where(a, i, slot.run),
            live=slot.live | a,
            state=_where(a, fresh, slot.state),
            params=_where(a, run.params, slot.params) if per_run_params else None,
            solver=_where(a, run.solver, slot.solver) if per_run_solver else None,
        )
        return slot

    slots = lax.cond(jnp.any(assign), lambda s: jax.vmap(load)(s, assign, idx), lambda s: s, slots)

    # 3. prepare the next solve
    need = assign | (solved & ~ended)

    def prepare_solve(slot, n):
        params, sp = params_of(slot)
        nxt = prepare(loop, params, slot.state)
        ocp, solve = start(nxt.ocp, settings, sp, nxt.warm, trusted_model=trusted)
        return slot._replace(
            guidance=_where(n, nxt.guidance, slot.guidance),
            ocp=_where(n, _strip_model(loop, ocp), slot.ocp),
            hard=jnp.where(n, nxt.hard, slot.hard),
            solve=_where(n, solve, slot.solve),
            nav=_where(n, nxt.nav, slot.nav),
        )

    slots = lax.cond(jnp.any(need), lambda s: jax.vmap(prepare_solve)(s, need), lambda s: s, slots)
    # a free slot's solve stays frozen
    core = slots.solve.core
    slots = slots._replace(
        solve=slots.solve._replace(core=core._replace(done=core.done | ~slots.live))
    )

    # 4. solver iterations
    def iterations(slot):
        params, sp = params_of(slot)
        ocp = ocp_of(slot, params)

        def body(_, st):
            return iterate(ocp, st, settings, sp)

        return slot._replace(solve=lax.fori_loop(0, cfg.iterations, body, slot.solve))

    slots = jax.vmap(iterations)(slots)
    return slots, ended, old_run, result


@functools.lru_cache(maxsize=64)
def _build(loop: Loop, cfg: EngineConfig, source_fn):
    """The jitted segment function (cached: one compile per loop, engine config and queue
    function, whatever the data), its slots sharded over ``cfg.devices`` devices
    (``shard_map``): every device runs the one-device segment on its slots; device d takes
    queue positions d, d + D, d + 2 D, ... (its local run i is position d + D i). The engine
    state has a leading device axis; no communication between devices. One device takes the
    same path (a one-device mesh), so that a run's bits do not depend on the number of
    devices."""
    from jax.sharding import PartitionSpec as P

    D = cfg.devices

    def strided(data, i):
        d = lax.axis_index(_AXIS)
        return source_fn(data, d + D * i)

    seg = _segment(loop, cfg.per_device, strided)

    def local(eng, source_data, shared_params, shared_sp, max_ticks):
        eng = jax.tree.map(lambda a: a[0], eng)
        eng = seg(eng, source_data, shared_params, shared_sp, max_ticks)
        return jax.tree.map(lambda a: a[None], eng)

    return jax.jit(
        jax.shard_map(
            local,
            mesh=_mesh(cfg),
            in_specs=(P(_AXIS), P(), P(), P(), P()),
            out_specs=P(_AXIS),
            check_vma=False,
        )
    )


_AXIS = "slots"


def _mesh(cfg: EngineConfig):
    devices = jax.local_devices()
    if cfg.devices > len(devices):
        raise ValueError(
            f"devices must be <= {len(devices)} (jax.local_devices() here), got {cfg.devices}; "
            "on a CPU, XLA_FLAGS=--xla_force_host_platform_device_count=N makes N devices"
        )
    return jax.sharding.Mesh(np.asarray(devices[: cfg.devices]), (_AXIS,))


def _segment(loop: Loop, cfg: EngineConfig, source_fn):
    """The segment function of one device (not jitted)."""
    C, n_chunks, R = cfg.chunk_size, cfg.n_chunks, cfg.ring_size

    def segment(eng: EngineState, source_data, shared_params, shared_sp, max_ticks):
        def source(i):
            return source_fn(source_data, i)

        def tick(eng: EngineState):
            slots = eng.slots
            # hand out runs to free slots, in slot order, while the ring has room
            free = ~slots.live
            order = jnp.cumsum(free) - 1
            cand = eng.next_run + jnp.arange(cfg.n_slots)
            room = (eng.ring_run[cand % R] < 0) & (cand < eng.n_runs)
            avail = jnp.sum(jnp.cumprod(room.astype(jnp.int32)))
            assign = free & (order < avail)
            idx = jnp.where(assign, eng.next_run + order, 0).astype(jnp.int32)
            n_assigned = jnp.sum(assign)
            stalled = (jnp.sum(free) > n_assigned) & (eng.next_run + n_assigned < eng.n_runs)
            # reserve the ring entries of the new runs
            pos = jnp.where(assign, idx % R, R)
            ring_run = eng.ring_run.at[pos].set(idx, mode="drop")

            def one_chunk(carry, c):
                slots, ring, ring_done = carry
                sl = jax.tree.map(lambda a: lax.dynamic_slice_in_dim(a, c * C, C), slots)
                asg = lax.dynamic_slice_in_dim(assign, c * C, C)
                ix = lax.dynamic_slice_in_dim(idx, c * C, C)
                busy = jnp.any(sl.live | asg)

                def work(args):
                    sl, asg, ix, ring, ring_done = args
                    new, ended, run, res = _chunk_tick(
                        loop, cfg, shared_params, shared_sp, source, sl, asg, ix
                    )
                    wpos = jnp.where(ended, run % R, R)
                    ring = jax.tree.map(lambda r, v: r.at[wpos].set(v, mode="drop"), ring, res)
                    ring_done = ring_done.at[wpos].set(True, mode="drop")
                    return new, ring, ring_done

                def skip(args):
                    sl, _, _, ring, ring_done = args
                    return sl, ring, ring_done

                new, ring, ring_done = lax.cond(busy, work, skip, (sl, asg, ix, ring, ring_done))
                slots = jax.tree.map(
                    lambda a, v: lax.dynamic_update_slice_in_dim(a, v, c * C, 0), slots, new
                )
                return (slots, ring, ring_done), None

            (slots, ring, ring_done), _ = lax.scan(
                one_chunk, (slots, eng.ring, eng.ring_done), jnp.arange(n_chunks)
            )
            return EngineState(
                slots=slots,
                next_run=(eng.next_run + n_assigned).astype(jnp.int32),
                n_runs=eng.n_runs,
                ring_run=ring_run,
                ring_done=ring_done,
                ring=ring,
                ticks=(eng.ticks + 1).astype(jnp.int32),
                stalled=stalled,
            )

        def cond(c):
            eng, t = c
            pending = (eng.next_run < eng.n_runs) | jnp.any(eng.slots.live)
            return pending & (t < max_ticks) & ~eng.stalled

        eng = eng._replace(stalled=jnp.asarray(False))
        eng, _ = lax.while_loop(cond, lambda c: (tick(c[0]), c[1] + 1), (eng, 0))
        return eng

    return segment


def _compact(eng: EngineState) -> EngineState:
    """Pack the live slots into the first chunks (stable order)."""
    perm = jnp.argsort(~eng.slots.live, stable=True)
    return eng._replace(slots=jax.tree.map(lambda a: a[perm], eng.slots))


_compact_sharded = jax.jit(jax.vmap(_compact))


def _like(ref, host):
    """``host`` (NumPy) placed like the device array ``ref`` (same sharding)."""
    return jax.device_put(jnp.asarray(host, ref.dtype), ref.sharding)


@functools.lru_cache(maxsize=64)
def _slot_builder(loop: Loop, source_fn, per_run_params: bool, per_run_solver: bool):
    def build(data, params, sp):
        src = functools.partial(source_fn, data)
        slot = _empty_slot(loop, params, sp, src, per_run_params, per_run_solver)
        ring0 = metrics(loop, slot.params if per_run_params else params, slot.state)
        return slot, ring0

    return jax.jit(build)


def _initial_state(loop, config: EngineConfig, source: Source, params, sp, n_runs):
    """One engine state per device, stacked on a sharded leading axis."""
    D = config.devices
    per = [
        _initial_state_one(loop, config.per_device, source, params, sp, (n_runs - d + D - 1) // D)
        for d in range(D)
    ]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *per)
    sharding = jax.sharding.NamedSharding(_mesh(config), jax.sharding.PartitionSpec(_AXIS))
    return jax.device_put(stacked, sharding)


def _initial_state_one(loop, config: EngineConfig, source: Source, params, sp, n_runs):
    probe = jax.eval_shape(functools.partial(source.fn, source.data), jnp.asarray(0))
    build = _slot_builder(loop, source.fn, probe.params is not None, probe.solver is not None)
    slot0, res0 = build(source.data, params, sp)
    B, R = config.n_slots, config.ring_size
    # strong types: the segment's outputs must have exactly the types of its inputs, or every
    # segment after the first would trace and compile again
    slot0 = jax.tree.map(lambda a: jnp.asarray(a, dtype=a.dtype), slot0)
    return EngineState(
        slots=jax.tree.map(lambda a: jnp.broadcast_to(a, (B, *a.shape)), slot0),
        next_run=jnp.asarray(0, jnp.int32),
        n_runs=jnp.asarray(n_runs, jnp.int32),
        ring_run=jnp.full(R, -1, jnp.int32),
        ring_done=jnp.zeros(R, bool),
        ring=jax.tree.map(lambda a: jnp.zeros((R, *a.shape), a.dtype), res0),
        ticks=jnp.asarray(0, jnp.int32),
        stalled=jnp.asarray(False),
    )


def run_batch(
    loop: Loop,
    source: Callable,
    n_runs: int,
    params=None,
    solver_params: SolverParams | None = None,
    config: EngineConfig = EngineConfig(),
    on_results: Callable | None = None,
    progress: Callable | None = None,
) -> dict:
    """Fly ``n_runs`` runs through ``config.slots`` slots; return their metrics by run index.

    Args:
        loop: the static closed loop (family + configuration).
        source: run index (traced int) -> :class:`RunInputs`; e.g. :func:`arrays_source`.
        n_runs: number of runs in the queue.
        params: the family parameters shared by every run whose ``RunInputs.params`` is None.
        solver_params: shared solver parameters (default: the settings' defaults).
        config: :class:`EngineConfig`.
        on_results: called as ``on_results(indices, metrics)`` (NumPy) after every segment
            with the runs finished in it (e.g. to write them to disk as they come).
        progress: called as ``progress(done, n_runs)`` after every segment.

    Returns:
        {"run": (n,) indices, "metrics": Metrics of NumPy arrays with a leading run axis in
        run-index order, "ticks": ticks, "seconds": wall time}.
    """
    if loop.config.settings.backend != "rvdjax":
        raise ValueError("the batch engine runs the rvdjax solver; use fly() for Clarabel")
    if n_runs < 1:
        raise ValueError(f"n_runs must be >= 1, got {n_runs}")
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    if not isinstance(source, Source):
        raise ValueError("source must be a rvdjax.loop.engine.Source (e.g. arrays_source(...))")
    probe = jax.eval_shape(functools.partial(source.fn, source.data), jnp.asarray(0))
    if probe.params is None and params is None:
        raise ValueError("params must be given when the source gives no per-run parameters")
    eng = _initial_state(loop, config, source, params, sp, n_runs)
    segment = _build(loop, config, source.fn)
    D = config.devices  # every engine array has a leading device axis
    collected_idx, collected = [], []
    done = 0
    t0 = time.perf_counter()
    while done < n_runs:
        eng = segment(eng, source.data, params, sp, config.ticks_per_segment)
        ring_done = np.asarray(eng.ring_done)
        if ring_done.any():
            dev, pos = np.nonzero(ring_done)
            local = np.asarray(eng.ring_run)[dev, pos]
            idx = dev + D * local
            res = jax.tree.map(lambda a, dev=dev, pos=pos: np.asarray(a)[dev, pos], eng.ring)
            collected_idx.append(idx)
            collected.append(res)
            done += len(idx)
            if on_results is not None:
                on_results(idx, res)
            ring_run = np.asarray(eng.ring_run).copy()
            ring_run[dev, pos] = -1
            eng = eng._replace(
                ring_run=_like(eng.ring_run, ring_run),
                ring_done=_like(eng.ring_done, np.zeros_like(ring_run, bool)),
            )
        if progress is not None:
            progress(done, n_runs)
        queue_empty = np.all(np.asarray(eng.next_run) >= np.asarray(eng.n_runs))
        if queue_empty and done < n_runs:
            eng = _compact_sharded(eng)
    idx = np.concatenate(collected_idx)
    order = np.argsort(idx)
    merged = jax.tree.map(lambda *a: np.concatenate(a)[order], *collected)
    return {
        "run": idx[order],
        "metrics": merged,
        "ticks": int(np.max(np.asarray(eng.ticks))),
        "seconds": time.perf_counter() - t0,
    }


def compile_engine(
    loop: Loop, source: Source, params=None, solver_params=None, config=EngineConfig()
) -> float:
    """Compile the engine's programs for ``loop``, the queue's function and ``config`` without
    flying (a later :func:`run_batch` with the same shapes reuses them); returns XLA's planned
    memory of the segment program [MB]: arguments + outputs + temporaries, set by the slots
    and the ring, not by the number of runs in the queue."""
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    eng = _initial_state(loop, config, source, params, sp, 1)
    compiled = (
        _build(loop, config, source.fn)
        .lower(eng, source.data, params, sp, config.ticks_per_segment)
        .compile()
    )
    try:
        m = compiled.memory_analysis()
        return (m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes) / 2**20
    except Exception:  # memory analysis is backend dependent
        return float("nan")


def fly_batch(
    loop: Loop,
    params,
    x0s,
    keys=None,
    solver_params: SolverParams | None = None,
    config: EngineConfig = EngineConfig(),
    progress: Callable | None = None,
) -> Metrics:
    """Fly one run per initial state in ``x0s`` (n, nx) with shared ``params``; the metrics
    of every run (NumPy, leading run axis)."""
    x0s = jnp.asarray(x0s)
    out = run_batch(
        loop,
        arrays_source(x0s, keys),
        x0s.shape[0],
        params=params,
        solver_params=solver_params,
        config=config,
        progress=progress,
    )
    return out["metrics"]
