"""The batch engine's segment of ticks on a device (:func:`_segment`): every tick hands
runs to free slots, refreshes the slots that need it (the step's end, a new run, the next
solve's start) and runs the solver iterations; and each device's share of the queue."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from rvdjax.loop.engine.config import EngineConfig, default_platform
from rvdjax.loop.engine.slots import (
    Block,
    EngineState,
    Slot,
    _strip_model,
    _with_model,
    model_of,
    table_of,
)
from rvdjax.loop.kernel import (
    Loop,
    Prepared,
    advance,
    init,
    metrics,
    prepare,
)
from rvdjax.solver import carries_system, finish, finished, freeze, iterate, start, with_system
from rvdjax.solver.platform import cuda_or_default


def _where(c, a, b):
    return jax.tree.map(lambda x, y: jnp.where(c, x, y), a, b)


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

    def ocp_of(self, slot, params):
        return self.problem_of(slot, params)[0]

    def problem_of(self, slot, params):
        """The slot's OCP and its model table (:func:`table_of`)."""
        model = model_of(self.loop, params, slot.guidance)
        return _with_model(slot.ocp, model), table_of(model)


@jax.named_scope("refresh")
def _refresh_group(ctx: _Ctx, source, slots: Slot, solved, assigned, seq, inputs_at):
    """The refresh of a group of slots (one vmap per phase): the end of the step whose solve
    finished, a new run for an assigned free slot, the next solve's start. Returns
    (slots, ended, metrics). ``inputs_at``: seq -> index into the queue's data."""
    loop = ctx.loop
    settings = loop.config.settings

    def step_done(slot, solved):
        params, sp = ctx.params_of(slot)
        ocp = ctx.ocp_of(slot, params)
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
        model = model_of(loop, params, nxt.guidance)
        trusted = model is not None  # the system is formed at each tick (_iterate_chunk)
        ocp, solve = start(nxt.ocp, settings, sp, nxt.warm, trusted_model=trusted, in_kernels=False)
        return slot._replace(
            guidance=_where(n, nxt.guidance, slot.guidance),
            ocp=_where(n, _strip_model(ocp, model), slot.ocp),
            hard=jnp.where(n, nxt.hard, slot.hard),
            solve=_where(n, solve, slot.solve),
            nav=_where(n, nxt.nav, slot.nav),
        )

    slots = lax.cond(jnp.any(need), lambda s: jax.vmap(prepare_solve)(s, need), lambda s: s, slots)
    slots = slots._replace(solve=freeze(slots.solve, ~slots.live))  # a free slot idles
    return slots, ended, result


@jax.named_scope("iterations")
def _iterate_chunk(ctx: _Ctx, cfg: EngineConfig, slots: Slot) -> Slot:
    """``cfg.iterations`` solver iterations of every slot. On a CUDA GPU the slot's guidance
    passes an optimisation barrier with the iterate in each iteration, so that the model it
    rebuilds (:func:`~rvdjax.loop.engine.slots.model_of`: thesis-vbar's from the phase) is
    not hoisted out of the loop and stored, but computed in each fusion that reads it: a tenth
    fewer bytes a thesis-vbar tick (docs/benchmark.md). The kernels' model tables, the
    parameters' alone, are built once before the iterations. On the CPU the hoisted model
    stays (as fast there).

    Where the Newton step's form carries the Newton system from one iteration to the next
    (:func:`~rvdjax.solver.carries_system`: the step's kernel forms the next one), the tick
    forms it once before its iterations and drops the last one's: the slots hold no system
    between ticks, which the refresh would otherwise form and move, with the slots first.
    (The last iteration's step without the system saves its writes and reads too, but as an
    iteration of its own outside the loop, its kernels compiled again: 125 s instead of 74
    for thesis-vbar's engine program here; docs/benchmark.md.)"""
    loop = ctx.loop
    settings = loop.config.settings

    def iterations(slot):
        params, sp = ctx.params_of(slot)
        table0 = table_of(model_of(loop, params, slot.guidance))

        def problem(g):
            ocp, table = ctx.problem_of(slot._replace(guidance=g), params)
            if table is not None:
                # the tables (the parameters' alone) built once a tick, not at each
                # iteration: six launches an iteration on a GPU (docs/benchmark.md)
                table = table0._replace(index=table.index)
            return ocp, table

        def body(_, st):
            g, st = cuda_or_default(
                (slot.guidance, st), cuda=lax.optimization_barrier, default=lambda gs: gs
            )
            ocp, table = problem(g)
            return iterate(ocp, settings, sp, st, table)

        if not carries_system(settings):
            return slot._replace(solve=lax.fori_loop(0, cfg.iterations, body, slot.solve))
        ocp, table = problem(slot.guidance)
        st = lax.fori_loop(0, cfg.iterations, body, with_system(ocp, settings, slot.solve, table))
        return slot._replace(solve=st._replace(core=st.core._replace(system=None)))

    return jax.vmap(iterations)(slots)


def _take(tree, ids, last=False):
    """Rows ``ids`` of every array (slots first), of slots stored last (``last``) too."""
    if last:
        return jax.tree.map(lambda a: jnp.moveaxis(jnp.take(a, ids, -1, mode="clip"), -1, 0), tree)
    return jax.tree.map(lambda a: jnp.take(a, ids, axis=0, mode="clip"), tree)


#: Slot arrays of at most this many bytes a slot are written back from a refresh group by a
#: select over every slot, larger ones by a scatter of the group's rows (see :func:`_put`).
SMALL_LEAF_BYTES = 256


def _put(tree, ids, valid, new, last=False):
    """``tree`` with rows ``ids`` (where ``valid``; distinct) replaced by ``new``'s. A scatter
    is a kernel launch of its own on a GPU, one per array: the 71 arrays of a thesis-vbar slot
    were 71 of the tick's 489 launches (``sweeps/gpu_traffic.py engine``). The small ones
    (counters, flags, the state; :data:`SMALL_LEAF_BYTES` a slot) are instead selected from
    the group's rows for every slot, elementwise work that XLA fuses across arrays; the large
    ones (the OCP's rows, the iterate) keep the scatter, which moves the group's rows only.
    Either way the same values. ``last``: ``tree``'s slots are its arrays' last axis (``new``'s
    still the first)."""
    n = jax.tree.leaves(tree)[0].shape[-1 if last else 0]
    g = ids.shape[0]
    pos = jnp.where(valid, ids, n)
    # where each slot's new row is in the group (g: not in it)
    inv = jnp.full((n,), g, jnp.int32).at[pos].set(jnp.arange(g, dtype=jnp.int32), mode="drop")
    hit, at = inv < g, jnp.minimum(inv, g - 1)

    def put(a, v):
        per_slot = a.dtype.itemsize * math.prod(a.shape[:-1] if last else a.shape[1:])
        big = per_slot > SMALL_LEAF_BYTES or jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key)
        if last:
            v = jnp.moveaxis(v, 0, -1)
            if big:
                return a.at[..., pos].set(v, mode="drop")
            return jnp.where(hit, jnp.take(v, at, axis=-1), a)
        if big:
            return a.at[pos].set(v, mode="drop")
        return jnp.where(hit.reshape((n,) + (1,) * (a.ndim - 1)), jnp.take(v, at, axis=0), a)

    return jax.tree.map(put, tree, new)


def _slots_last(cfg: EngineConfig) -> bool:
    """Whether the segment's loop over ticks keeps the slots as its arrays' last axis: on an
    accelerator, with the compacted refresh and the slots in one chunk (the accelerator
    defaults). The GPU kernels read the slots batch-last ([stage][entry][slot]): with the
    slots first in the tick loop's arrays, XLA transposed the iterate and the OCP's rows in
    and out of the solver's loop in every tick (counted for an H100: about 110 KB a
    thesis-vbar slot and 22 launches of a tick's 405; ``sweeps/gpu_traffic.py engine``).
    Stored last, they are the layout the kernels read; the refresh gathers and scatters its
    group along that axis. The same values either way (tests); the CPU keeps the slots
    first."""
    platform = cfg.platform or default_platform()
    return cfg.refresh == "compacted" and cfg.n_chunks == 1 and platform != "cpu"


def _moved(tree, src: int, dst: int):
    return jax.tree.map(lambda a: jnp.moveaxis(a, src, dst), tree)


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
    last = _slots_last(cfg)

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
            stored = eng.slots  # slots last where `last`
            slots = _moved(stored, -1, 0) if last else stored
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
                    sl = _take(slots, ids, last)
                    sv = jnp.take(solved, ids) & valid
                    asg = jnp.take(assign, ids) & valid
                    sq = jnp.take(seq, ids)
                    new, ring, ring_done = refresh(sl, sv, asg, sq, ring, ring_done)
                    return g + 1, _put(slots, ids, valid, new, last), ring, ring_done

                _, slots, ring, ring_done = lax.while_loop(
                    lambda c: c[0] < n_groups,
                    one_group,
                    (jnp.asarray(0, n_groups.dtype), stored, eng.ring, eng.ring_done),
                )

                # solver iterations, chunk by chunk (a chunk with no run in flight is skipped)
                if last:
                    slots = _moved(_iterate_chunk(ctx, cfg, _moved(slots, -1, 0)), 0, -1)
                elif n_chunks == 1:
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
        if not last:
            eng, _ = lax.while_loop(cond, lambda c: (tick(c[0]), c[1] + 1), (eng, 0))
            return eng

        def moved(e, src, dst):
            return e._replace(slots=_moved(e.slots, src, dst))

        eng, _ = lax.while_loop(
            lambda c: cond((moved(c[0], -1, 0), c[1])),
            lambda c: (tick(c[0]), c[1] + 1),
            (moved(eng, 0, -1), 0),
        )
        return moved(eng, -1, 0)

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


def _positions(cfg: EngineConfig, dev, D: int, seq):
    """Queue positions of device ``dev``'s sequence numbers (NumPy)."""
    if cfg.assign == "lane":
        C = cfg.chunk_size
        return ((seq // C) * D + dev) * C + seq % C
    return dev + D * seq
