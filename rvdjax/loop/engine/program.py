"""The batch engine's device program: the slots, the tick (refresh and solver iterations) and
a segment of ticks as one jitted function (:func:`segment_program`), its state and the
queue's inputs (:class:`Source`, :class:`Block`)."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from rvdjax.loop.engine.config import EngineConfig, RunInputs, default_platform
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
from rvdjax.solver import SolverParams, SolveState, finish, finished, freeze, iterate, start
from rvdjax.solver.driver import MODEL_FIELDS


def slot_bytes(loop: Loop, source: Source, params=None, solver_params=None) -> int:
    """Bytes of one slot's state for this loop and queue (from shapes only: nothing is
    compiled or run)."""
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    probe = jax.eval_shape(functools.partial(source.fn, source.data), jnp.asarray(0))
    shape = jax.eval_shape(
        lambda data, p, s: _empty_slot(
            loop,
            p,
            s,
            functools.partial(source.fn, data),
            probe.params is not None,
            probe.solver is not None,
        ),
        source.data,
        params,
        sp,
    )
    leaves = jax.tree.leaves(shape)
    return int(sum(math.prod(a.shape) * _itemsize(a.dtype) for a in leaves))


def _itemsize(dtype) -> int:
    if jnp.issubdtype(dtype, jax.dtypes.prng_key):
        return 8  # a threefry key: two uint32
    return jnp.dtype(dtype).itemsize


class Slot(NamedTuple):
    """One slot: its run, the loop state, the prepared step and the solve in progress."""

    run: jnp.ndarray  # () the run's sequence number on this device (-1: free)
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
    next_seq: jnp.ndarray  # (L,) next sequence number per lane queue (L = lanes or 1)
    ring_run: jnp.ndarray  # (R,) sequence number held by each ring entry (-1: free)
    ring_done: jnp.ndarray  # (R,) the entry holds a finished result
    ring: Metrics  # (R, ...) finished results
    ticks: jnp.ndarray  # () ticks so far
    stalled: jnp.ndarray  # () a free slot could not take a run (ring full, or the block
    #                       handed out with more to come): collect


class Source(NamedTuple):
    """A queue of runs: ``fn(data, i) -> RunInputs`` for index i (a traced int) into
    ``data``. ``fn`` is static (hashable: a module-level function), ``data`` a pytree of
    arrays passed to the compiled program, so a new queue of the same shapes does not
    recompile."""

    fn: Callable
    data: Any


class Block(NamedTuple):
    """Part of a queue: ``data`` for :class:`Source`'s function, holding the runs at queue
    positions ``start`` .. ``stop - 1`` (index ``position - start`` into ``data``). Every block
    of a queue has the same array shapes (pad the last one)."""

    data: Any
    start: int
    stop: int


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
    """A free slot with the right shapes (built from the queue's first entry, then marked
    free)."""
    run = source(jnp.asarray(0))
    p = run.params if per_run_params else params
    s = run.solver if per_run_solver else sp
    state = init(loop, p, run.x0, run.key)
    prep = prepare(loop, p, state)
    ocp, solve_state = start(
        prep.ocp, loop.config.settings, s, prep.warm, trusted_model=loop.family.model is not None
    )
    ocp = _strip_model(loop, ocp)
    solve_state = freeze(solve_state)
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


class _Ctx(NamedTuple):
    """What the per-slot functions of a segment share."""

    loop: Loop
    shared_params: Any
    shared_sp: Any
    per_run_params: bool
    per_run_solver: bool

    def params_of(self, slot):
        return (
            slot.params if self.per_run_params else self.shared_params,
            slot.solver if self.per_run_solver else self.shared_sp,
        )

    def ocp_of(self, slot, params, shared_model):
        fam = self.loop.family
        if fam.model is None:
            return slot.ocp
        if shared_model is None:
            shared_model = fam.model(params, self.loop.config.family_config)
        model = shared_model
        return _with_model(self.loop, slot.ocp, model)

    def shared_model(self):
        """The model shared by every slot (unbatched: one large product per stage for all
        slots), or None."""
        fam = self.loop.family
        if fam.model is None or self.per_run_params:
            return None
        return fam.model(self.shared_params, self.loop.config.family_config)


@jax.named_scope("refresh")
def _refresh_group(ctx: _Ctx, source, slots: Slot, solved, assigned, seq, inputs_at):
    """The refresh of a group of slots (one vmap per phase): the end of the step whose solve
    finished, a new run for an assigned free slot, the next solve's start. Returns
    (slots, ended, metrics). ``inputs_at``: seq -> index into the queue's data."""
    loop = ctx.loop
    settings = loop.config.settings
    trusted = loop.family.model is not None
    shared_model = ctx.shared_model()

    def step_done(slot, solved):
        params, sp = ctx.params_of(slot)
        ocp = ctx.ocp_of(slot, params, shared_model)
        sol = finish(ocp, settings, sp, slot.solve)
        prep = Prepared(slot.guidance, ocp, slot.hard, None, slot.nav)
        stepped, _ = advance(loop, params, sp, slot.state, prep, sol)
        state = _where(solved, stepped, slot.state)
        ended = solved & ~state.active
        return slot._replace(state=state, live=slot.live & ~ended), ended

    slots, ended = jax.vmap(step_done)(slots, solved)
    result = jax.vmap(lambda s: metrics(loop, ctx.params_of(s)[0], s.state))(slots)

    def load(slot, a, q):
        run = source(inputs_at(q))
        params = run.params if ctx.per_run_params else ctx.shared_params
        fresh = init(loop, params, run.x0, run.key)
        return slot._replace(
            run=jnp.where(a, q, slot.run),
            live=slot.live | a,
            state=_where(a, fresh, slot.state),
            params=_where(a, run.params, slot.params) if ctx.per_run_params else None,
            solver=_where(a, run.solver, slot.solver) if ctx.per_run_solver else None,
        )

    slots = lax.cond(
        jnp.any(assigned), lambda s: jax.vmap(load)(s, assigned, seq), lambda s: s, slots
    )
    need = assigned | (solved & ~ended)

    def prepare_solve(slot, n):
        params, sp = ctx.params_of(slot)
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
    slots = slots._replace(solve=freeze(slots.solve, ~slots.live))  # a free slot idles
    return slots, ended, result


@jax.named_scope("iterations")
def _iterate_chunk(ctx: _Ctx, cfg: EngineConfig, slots: Slot) -> Slot:
    loop = ctx.loop
    settings = loop.config.settings
    shared_model = ctx.shared_model()

    def iterations(slot):
        params, sp = ctx.params_of(slot)
        ocp = ctx.ocp_of(slot, params, shared_model)

        def body(_, st):
            return iterate(ocp, settings, sp, st)

        return slot._replace(solve=lax.fori_loop(0, cfg.iterations, body, slot.solve))

    return jax.vmap(iterations)(slots)


def _take(tree, ids):
    return jax.tree.map(lambda a: jnp.take(a, ids, axis=0, mode="clip"), tree)


def _put(tree, ids, valid, new):
    n = jax.tree.leaves(tree)[0].shape[0]
    pos = jnp.where(valid, ids, n)
    return jax.tree.map(lambda a, v: a.at[pos].set(v, mode="drop"), tree, new)


def _slice(tree, start, size):
    return jax.tree.map(lambda a: lax.dynamic_slice_in_dim(a, start, size), tree)


def _unslice(tree, start, new):
    return jax.tree.map(lambda a, v: lax.dynamic_update_slice_in_dim(a, v, start, 0), tree, new)


def _segment(loop: Loop, cfg: EngineConfig, source_fn):
    """The segment function of one device (not jitted). The device's index d among D devices
    is data (the last two arguments): every device, and one device alone, runs the same
    program."""
    C, n_chunks, R = cfg.chunk_size, cfg.n_chunks, cfg.ring_size
    S = cfg.n_slots
    G = cfg.group_size

    def position(seq, d, D):
        """The queue position of this device's sequence number ``seq``: with lanes, runs
        (j D + d) C + l for lane l = seq mod C and j = seq // C; without, d + D seq."""
        if cfg.assign == "lane":
            return ((seq // C) * D + d) * C + seq % C
        return d + D * seq

    def segment(
        eng: EngineState, source_data, base, limit, more, shared_params, shared_sp, ticks, d, D
    ):
        probe = jax.eval_shape(lambda: source_fn(source_data, jnp.asarray(0)))
        per_run = (probe.params is not None, probe.solver is not None)
        ctx = _Ctx(loop, shared_params, shared_sp, *per_run)

        def source(i):
            return source_fn(source_data, i)

        def inputs_at(seq):
            return position(seq, d, D) - base

        # this device's queue: the sequence numbers below `end` (per lane, or one queue)
        end = _local_end(cfg, limit, d, D, jnp)

        def tick(eng: EngineState):
            slots = eng.slots
            free = ~slots.live
            # hand out runs to free slots in slot order (per lane queue), while the ring has room
            if cfg.assign == "lane":
                f = free.reshape(n_chunks, C)
                order = jnp.cumsum(f, axis=0) - 1  # rank of a free slot in its lane
                cand = eng.next_seq[None, :] + C * order
                room = (eng.ring_run[cand % R] < 0) & (cand < end[None, :])
                ok = f & (jnp.cumprod(room | ~f, axis=0).astype(bool))
                assign = ok.reshape(S)
                seq = jnp.where(assign, cand.reshape(S), 0).astype(jnp.int32)
                n_lane = jnp.sum(ok, axis=0)
                next_seq = eng.next_seq + C * n_lane
                exhausted = eng.next_seq + C * n_lane >= end
                starved = jnp.any(f & ~ok & (cand >= end[None, :]))
                blocked = jnp.any(f & ~ok & (cand < end[None, :]))
                starved = starved & jnp.all(exhausted)
            else:
                order = jnp.cumsum(free) - 1
                cand = eng.next_seq[0] + jnp.arange(S)
                room = (eng.ring_run[cand % R] < 0) & (cand < end[0])
                avail = jnp.sum(jnp.cumprod(room.astype(jnp.int32)))
                assign = free & (order < avail)
                seq = jnp.where(assign, eng.next_seq[0] + order, 0).astype(jnp.int32)
                n_assigned = jnp.sum(assign)
                next_seq = eng.next_seq + n_assigned
                left = eng.next_seq[0] + n_assigned < end[0]
                blocked = (jnp.sum(free) > n_assigned) & left
                starved = (jnp.sum(free) > n_assigned) & ~left
            stalled = blocked | (more & starved)
            # reserve the ring entries of the new runs
            ring_run = eng.ring_run.at[jnp.where(assign, seq % R, R)].set(seq, mode="drop")

            solved = jax.vmap(lambda s: s.live & finished(loop.config.settings, s.solve))(slots)
            todo = solved | assign

            @jax.named_scope("ring")
            def write(ring, ring_done, ended, run, res):
                wpos = jnp.where(ended, run % R, R)
                ring = jax.tree.map(lambda r, v: r.at[wpos].set(v, mode="drop"), ring, res)
                return ring, ring_done.at[wpos].set(True, mode="drop")

            def iterate_if_live(sl):
                if n_chunks == 1:
                    return _iterate_chunk(ctx, cfg, sl)
                return lax.cond(
                    jnp.any(sl.live), lambda s: _iterate_chunk(ctx, cfg, s), lambda s: s, sl
                )

            def refresh(sl, sv, asg, sq, ring, ring_done):
                new, ended, res = _refresh_group(ctx, source, sl, sv, asg, sq, inputs_at)
                ring, ring_done = write(ring, ring_done, ended, new.run, res)
                return new, ring, ring_done

            if cfg.refresh == "masked":
                # chunk by chunk: the refresh (skipped for a chunk with no slot to refresh)
                # and the solver iterations (skipped for a chunk with no run in flight), one
                # slice of the chunk's slots for both

                def one_chunk(c, carry):
                    slots, ring, ring_done = carry
                    sl = _slice(slots, c * C, C)
                    sv, asg, sq, td = (
                        lax.dynamic_slice_in_dim(a, c * C, C) for a in (solved, assign, seq, todo)
                    )

                    def work(args):
                        sl, ring, ring_done = args
                        return refresh(sl, sv, asg, sq, ring, ring_done)

                    sl, ring, ring_done = lax.cond(
                        jnp.any(td), work, lambda a: a, (sl, ring, ring_done)
                    )
                    sl = iterate_if_live(sl)
                    return _unslice(slots, c * C, sl), ring, ring_done

                if n_chunks == 1:
                    slots, ring, ring_done = one_chunk(0, (slots, eng.ring, eng.ring_done))
                else:
                    slots, ring, ring_done = lax.fori_loop(
                        0, n_chunks, one_chunk, (slots, eng.ring, eng.ring_done)
                    )
            else:
                if cfg.assign == "lane":
                    # lane-preserving groups: group g holds, in lane l, the g-th slot of lane
                    # l that needs a refresh
                    t = todo.reshape(n_chunks, C)
                    rank = jnp.cumsum(t, axis=0) - 1
                    chunk_of = jnp.broadcast_to(jnp.arange(n_chunks)[:, None], t.shape)
                    table = jnp.full((n_chunks, C), n_chunks, jnp.int32)
                    table = table.at[jnp.where(t, rank, n_chunks), jnp.arange(C)[None, :]].set(
                        chunk_of.astype(jnp.int32), mode="drop"
                    )
                    n_groups = jnp.max(jnp.sum(t, axis=0))

                    def ids_of(g):
                        row = lax.dynamic_index_in_dim(table, g, keepdims=False)
                        valid = row < n_chunks
                        return jnp.minimum(row, n_chunks - 1) * C + jnp.arange(C), valid

                else:
                    count = jnp.sum(todo)
                    packed = jnp.full(pl := G * math.ceil(S / G), S, jnp.int32)
                    packed = packed.at[jnp.where(todo, jnp.cumsum(todo) - 1, pl)].set(
                        jnp.arange(S, dtype=jnp.int32), mode="drop"
                    )
                    n_groups = (count + G - 1) // G

                    def ids_of(g):
                        row = lax.dynamic_slice_in_dim(packed, g * G, G)
                        valid = row < S
                        return jnp.minimum(row, S - 1), valid

                def one_group(carry):
                    g, slots, ring, ring_done = carry
                    ids, valid = ids_of(g)
                    sl = _take(slots, ids)
                    sv = jnp.take(solved, ids) & valid
                    asg = jnp.take(assign, ids) & valid
                    sq = jnp.take(seq, ids)
                    new, ring, ring_done = refresh(sl, sv, asg, sq, ring, ring_done)
                    return g + 1, _put(slots, ids, valid, new), ring, ring_done

                _, slots, ring, ring_done = lax.while_loop(
                    lambda c: c[0] < n_groups,
                    one_group,
                    (jnp.asarray(0, n_groups.dtype), slots, eng.ring, eng.ring_done),
                )

                # solver iterations, chunk by chunk (a chunk with no run in flight is skipped)
                if n_chunks == 1:
                    slots = _iterate_chunk(ctx, cfg, slots)
                else:

                    def iterate_chunk(c, slots):
                        return _unslice(slots, c * C, iterate_if_live(_slice(slots, c * C, C)))

                    slots = lax.fori_loop(0, n_chunks, iterate_chunk, slots)
            return EngineState(
                slots=slots,
                next_seq=next_seq.astype(jnp.int32),
                ring_run=ring_run,
                ring_done=ring_done,
                ring=ring,
                ticks=(eng.ticks + 1).astype(jnp.int32),
                stalled=stalled,
            )

        def cond(c):
            eng, t = c
            pending = jnp.any(eng.next_seq < end) | jnp.any(eng.slots.live)
            return pending & (t < ticks) & ~eng.stalled

        # the host has collected every finished result of the previous segment
        eng = eng._replace(
            stalled=jnp.asarray(False),
            ring_run=jnp.where(eng.ring_done, -1, eng.ring_run),
            ring_done=jnp.zeros_like(eng.ring_done),
        )
        eng, _ = lax.while_loop(cond, lambda c: (tick(c[0]), c[1] + 1), (eng, 0))
        return eng

    return segment


def _local_end(cfg: EngineConfig, limit, d, D: int, xp):
    """Device d's end of the queue: per lane the first sequence number not in it (or the
    one queue's). ``limit``: with lanes, the queue rows k (queue positions k C + l) per lane,
    of which device d flies k = d, d + D, ...; without, the queue's positions, of which it
    flies d, d + D, ..."""
    rows = xp.maximum(0, -((d - limit) // D))
    if cfg.assign == "lane":
        return rows * cfg.chunk_size + xp.arange(cfg.chunk_size)
    return rows


def _block_limit(cfg: EngineConfig, block: Block, lane_counts, n_runs: int):
    """The ``limit`` of a segment flying from ``block`` (see :func:`_local_end`)."""
    if cfg.assign == "lane":
        C = cfg.chunk_size
        return np.minimum(lane_counts, -(-block.stop // C)).astype(np.int32)
    return np.asarray([min(block.stop, n_runs)], np.int32)


def _devices(cfg: EngineConfig) -> list:
    platform = cfg.platform or default_platform()
    devices = jax.local_devices(backend=platform)
    if cfg.devices > len(devices):
        raise ValueError(
            f"devices must be <= {len(devices)} (local {platform} "
            f"devices here), got {cfg.devices}; on a CPU, "
            "XLA_FLAGS=--xla_force_host_platform_device_count=N makes N devices"
        )
    return devices[: cfg.devices]


def _build(loop: Loop, cfg: EngineConfig, source_fn):
    # the ticks per segment are an argument of the program, not part of it
    return _build_one(loop, dataclasses.replace(cfg.per_device, ticks_per_segment=1), source_fn)


@functools.lru_cache(maxsize=64)
def _build_one(loop: Loop, cfg: EngineConfig, source_fn):
    """The jitted segment function of one device (cached: one compile per loop, engine
    configuration of a device and queue function, whatever the data). Several devices run
    it each on its own slots and share of the queue, with no communication: the same
    program (JAX compiles a one-device program once and runs it on any device) and so the
    same bits as on one device. (A ``shard_map`` over the devices was partitioned by XLA:
    one of the solver's shared-model products took another layout, and the last bits of
    some runs differed from one device's.)"""
    return jax.jit(_segment(loop, cfg, source_fn))


def segment_program(loop: Loop, cfg: EngineConfig, source_fn):
    """The jitted segment of one device: what each device runs (for :func:`export_segment`
    and for reading its compiled program)."""
    return _build(loop, cfg, source_fn)


def _compact(cfg: EngineConfig):
    """Pack the live slots into the first chunks (stable order; with lanes, each slot stays
    in its lane)."""
    C, n = cfg.chunk_size, cfg.n_chunks

    def pack(eng: EngineState) -> EngineState:
        if cfg.assign == "lane":
            live = eng.slots.live.reshape(n, C)
            perm = jnp.argsort(~live, axis=0, stable=True) * C + jnp.arange(C)[None, :]
            perm = perm.reshape(-1)
        else:
            perm = jnp.argsort(~eng.slots.live, stable=True)
        return eng._replace(slots=jax.tree.map(lambda a: a[perm], eng.slots))

    return pack


@functools.lru_cache(maxsize=16)
def _compact_jit(cfg: EngineConfig):
    return jax.jit(_compact(cfg.per_device))


@functools.lru_cache(maxsize=64)
def _gather(size: int):
    """Pick ``size`` ring entries of one device's ring."""

    def take(ring, ring_run, pos):
        return jax.tree.map(lambda a: a[pos], ring), ring_run[pos]

    return jax.jit(take)


@functools.lru_cache(maxsize=64)
def _slot_builder(loop: Loop, source_fn, per_run_params: bool, per_run_solver: bool):
    def build(data, params, sp):
        src = functools.partial(source_fn, data)
        slot = _empty_slot(loop, params, sp, src, per_run_params, per_run_solver)
        ring0 = metrics(loop, slot.params if per_run_params else params, slot.state)
        return slot, ring0

    return jax.jit(build)


def _initial_state(loop, config: EngineConfig, source: Source, params, sp) -> list:
    """One engine state per device (on it)."""
    one = _initial_state_one(loop, config.per_device, source, params, sp)
    return [jax.device_put(one, d) for d in _devices(config)]


def _initial_state_one(loop, config: EngineConfig, source: Source, params, sp):
    probe = jax.eval_shape(functools.partial(source.fn, source.data), jnp.asarray(0))
    build = _slot_builder(loop, source.fn, probe.params is not None, probe.solver is not None)
    slot0, res0 = build(source.data, params, sp)
    B, R = config.n_slots, config.ring_size
    # strong types: the segment's outputs must have exactly the types of its inputs, or every
    # segment after the first would trace and compile again
    slot0 = jax.tree.map(lambda a: jnp.asarray(a, dtype=a.dtype), slot0)
    return EngineState(
        slots=jax.tree.map(lambda a: jnp.broadcast_to(a, (B, *a.shape)), slot0),
        next_seq=jnp.arange(config.lanes, dtype=jnp.int32),
        ring_run=jnp.full(R, -1, jnp.int32),
        ring_done=jnp.zeros(R, bool),
        ring=jax.tree.map(lambda a: jnp.zeros((R, *a.shape), a.dtype), res0),
        ticks=jnp.asarray(0, jnp.int32),
        stalled=jnp.asarray(False),
    )


def _positions(cfg: EngineConfig, dev, D: int, seq):
    """Queue positions of device ``dev``'s sequence numbers (NumPy)."""
    if cfg.assign == "lane":
        C = cfg.chunk_size
        return ((seq // C) * D + dev) * C + seq % C
    return dev + D * seq
