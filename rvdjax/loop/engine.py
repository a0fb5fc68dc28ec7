"""The batch engine: many closed-loop runs through a fixed set of slots.

B slots step together; a queue of runs (a function of the run's queue position) feeds them.
Every *tick*:

1. **refresh** the slots whose solve has finished and the free slots that take a run: the
   second half of the MPC step (:func:`rvdjax.loop.kernel.advance`: command, actuator, plant,
   guidance, accumulation); a run that ends (docked, out of steps, failed) writes its metrics
   to the result ring and frees its slot; a free slot takes the next run of the queue
   (auto-reset, as vectorised simulators do); the slot's next solve is prepared
   (:func:`rvdjax.loop.kernel.prepare` and the solver's ``start``). Only these slots are
   refreshed: gathered into groups (``refresh="compacted"``) or by chunk with the other slots
   masked (``"masked"``; a chunk with none is skipped, a real branch);
2. ``iterations`` solver iterations for every slot (:func:`rvdjax.solver.iterate`; a
   finished iterate is frozen), chunk by chunk (``chunk`` slots per ``vmap``, so that a
   chunk's working set stays in cache; a chunk with no run in flight is skipped).

A slot never waits for the slowest member of the batch: a solve that needs more iterations
continues on the next tick, and a slot whose run ended takes the next run.

**The same bits whatever the slots and devices.** A run's computation depends only on its
own inputs (parameters, initial state, PRNG key) and the solver's iterate is frozen once
finished, however the iterations were grouped. One more thing decides the last bits on a
CPU: the lane a run flies in. XLA's loops over the lanes of a chunk are vectorised, and
LLVM computes the last vector's lanes in a scalar epilogue that contracts multiplies and adds
into FMAs in other places than the vector body does (measured: ``thesis-vbar``, lanes 8-15 of
16 and 24-31 of 32 differ by an ulp in their keep-out normals, and 1e-12 m/s in delta-v a few
hundred steps on). So with ``assign="lane"`` (the CPU default) run r flies only in lane
r mod ``chunk`` of a chunk (each lane has its own queue of runs) and the refresh keeps every
slot in its lane: a run's bits then depend on the chunk width alone, not on the number of
slots, chunks or devices. ``assign="any"`` (accelerators) hands a run to the first free slot
and lets the compacted refresh pack the slots that need it.

Results are collected on the host between *segments* of ticks (:func:`run_stream`), so a long
study can write them as it goes; the device keeps only the slots and a ring of R finished
results (memory set by the slots, not by the number of runs). The queue may come in blocks
of inputs (host memory set by the block, not by the number of runs): a free slot reads its
run's inputs once, when it takes the run, so the next block replaces the current one as soon
as every run of the current block has been handed out.

:func:`auto_config` picks the engine's settings for the device (the CPU's measured defaults;
on an accelerator the slots from its memory, one chunk, the compacted refresh); its
:attr:`EngineConfig.chosen` says what it chose and why.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from rvdjax.devices import default_device
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

__all__ = [
    "RunInputs",
    "Source",
    "Block",
    "EngineConfig",
    "auto_config",
    "accelerator_slots",
    "default_platform",
    "slot_bytes",
    "run_batch",
    "run_stream",
    "fly_batch",
    "arrays_source",
    "compile_engine",
    "segment_program",
    "export_segment",
]


class RunInputs(NamedTuple):
    """What the queue gives for one run.

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


REFRESH = ("masked", "compacted")
ASSIGN = ("lane", "any")


@dataclasses.dataclass(frozen=True)
class EngineConfig:
    """Static engine configuration (:func:`auto_config` picks one for the device).

    Attributes:
        slots: B, runs in flight at once (rounded up to a whole number of chunks per device).
        chunk: slots per vmapped chunk (cache-sized on a CPU; all slots on an accelerator).
        iterations: solver iterations per slot per tick.
        ticks_per_segment: ticks between two collections of results on the host.
        ring: finished results kept on the device between collections (0: 4 x slots).
        devices: the slots are split over this many devices (the first ``devices`` of the
            platform's local devices), each running the one-device program on its share of
            the slots and of the queue, with no communication between devices.
        refresh: "masked" (every chunk with a slot to refresh runs the refresh for all its
            slots, the others masked) or "compacted" (the slots to refresh are gathered into
            groups of ``group`` and only those run it).
        group: compacted refresh: slots per group (0: ``chunk``); with ``assign="lane"`` a
            group is a chunk's width (one slot per lane).
        assign: "lane" (run r flies in lane r mod chunk: its bits do not depend on the
            number of slots or devices; module docstring) or "any" (the first free slot).
        platform: the devices' platform ("cpu", "gpu", ...; None: JAX's default backend).
        chosen: how the values were chosen (printed by studies; not part of the program).
    """

    slots: int = 256
    chunk: int = 32
    iterations: int = 3
    ticks_per_segment: int = 256
    ring: int = 0  # 0: 4 * slots
    devices: int = 1
    refresh: str = "masked"
    group: int = 0
    assign: str = "lane"
    platform: str | None = None
    chosen: str = dataclasses.field(default="", compare=False)

    def __post_init__(self):
        for name in ("slots", "chunk", "iterations", "ticks_per_segment", "devices"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("ring", "group"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                raise ValueError(f"{name} must be an integer >= 0, got {v!r}")
        if self.refresh not in REFRESH:
            raise ValueError(f"refresh must be one of {REFRESH}, got {self.refresh!r}")
        if self.assign not in ASSIGN:
            raise ValueError(f"assign must be one of {ASSIGN}, got {self.assign!r}")

    @property
    def per_device(self) -> EngineConfig:
        """The configuration of one device's share of the slots."""
        if self.devices == 1:
            return self
        return dataclasses.replace(self, slots=math.ceil(self.slots / self.devices), devices=1)

    @property
    def chunk_size(self) -> int:
        """Slots per chunk: ``chunk``, or all slots when fewer. With lanes a run's bits depend
        on this width (:func:`auto_config` keeps it at ``chunk``)."""
        return min(self.chunk, self.slots)

    @property
    def n_chunks(self) -> int:
        return math.ceil(self.slots / self.chunk_size)

    @property
    def n_slots(self) -> int:
        return self.n_chunks * self.chunk_size

    @property
    def group_size(self) -> int:
        if self.assign == "lane":
            return self.chunk_size
        return min(self.group or self.chunk_size, self.n_slots)

    @property
    def ring_size(self) -> int:
        return self.ring if self.ring else 4 * self.n_slots

    @property
    def lanes(self) -> int:
        """Independent run queues per device: one per lane, or one."""
        return self.chunk_size if self.assign == "lane" else 1

    def describe(self) -> str:
        """One line: the values and how they were chosen."""
        per = self.per_device
        text = (
            f"{per.n_slots * self.devices} slots ({self.devices} device(s) x {per.n_chunks} "
            f"chunk(s) of {per.chunk_size}), {self.iterations} solver iterations per tick, "
            f"{self.ticks_per_segment} ticks per segment, {self.refresh} refresh"
            + (f" in groups of {per.group_size}" if self.refresh == "compacted" else "")
            + f", runs assigned to {'their lane' if self.assign == 'lane' else 'any free slot'}"
            + f", platform {self.platform or default_platform()}"
        )
        return f"{text}; {self.chosen}" if self.chosen else text


# The CPU defaults, measured on one core of a 2-core x86-64 VM (docs/benchmark.md): chunks of
# 32 slots keep a chunk's working set in cache (16 and 64: 3-9 % slower an iteration), 3
# iterations per tick (4: within noise for thesis-vbar, 10-20 % slower for fastmpc-3d and
# spot-2d-a), 256 slots keep a core's chunks busy while runs finish at different times.
CPU_DEFAULTS = dict(slots=256, chunk=32, iterations=3, ticks_per_segment=256)
# On a CPU the masked refresh (one vmap per chunk, no gathers) was measured against the
# compacted one on the 2-core VM (docs/history.md, "A tick in few kernels").
CPU_REFRESH = "masked"
# Accelerators: one chunk of every slot (a kernel per operation for all slots; its launch
# latency, not the arithmetic, sets a tick's time), as many slots as memory allows up to
# ACCEL_MAX_SLOTS, the compacted refresh. Not measured on a GPU in this repository yet: the
# GPU benchmark (sweeps/gpu_study_benchmark.py) measures them.
ACCEL_MAX_SLOTS = 65536
ACCEL_MEMORY_SHARE = 0.5  # of the device's memory for the engine (slots, ring, temporaries)
ACCEL_TEMP_FACTOR = 8  # temporaries of a tick per byte of slot state (Riccati factors, steps)
ACCEL_ITERATIONS = 4  # fewer ticks per solve: a tick's fixed cost is kernel launches
ACCEL_TICKS = 128
ACCEL_REFRESH_SHARE = 4  # a refresh group holds slots / 4 (about a third solve per tick)


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


def _device_memory(device) -> int | None:
    try:
        stats = device.memory_stats() or {}
    except Exception:  # not every backend reports its memory
        return None
    return stats.get("bytes_limit") or stats.get("bytes_reservable_limit")


def default_platform() -> str:
    """The platform work goes to: that of ``jax.default_device`` when set (e.g. by the
    command line's ``--device``), else JAX's default backend."""
    return default_device().platform


def _pow2_floor(n: int) -> int:
    return 1 << max(0, int(n).bit_length() - 1)


def accelerator_slots(memory: int | None, slot_bytes: int | None) -> int:
    """Slots a device on an accelerator with ``memory`` bytes: ``ACCEL_MEMORY_SHARE`` of it
    over ``slot_bytes`` x ``ACCEL_TEMP_FACTOR``, a power of two from 256 to
    ``ACCEL_MAX_SLOTS`` (16384 when either is unknown)."""
    if not memory or not slot_bytes:
        return 16384
    fit = int(memory * ACCEL_MEMORY_SHARE // (slot_bytes * ACCEL_TEMP_FACTOR))
    return max(256, min(ACCEL_MAX_SLOTS, _pow2_floor(fit)))


def auto_config(
    *,
    platform: str | None = None,
    devices: int = 1,
    n_runs: int | None = None,
    slot_bytes: int | Callable[[], int] | None = None,
    **overrides,
) -> EngineConfig:
    """The engine's settings for the device; ``overrides`` (the :class:`EngineConfig` fields a
    user set; None: not set) take precedence. :attr:`EngineConfig.chosen` says how each value
    was chosen. ``slots`` (chosen or set) counts the slots of all ``devices`` together.

    On a CPU: the measured defaults per device (256 slots, chunks of 32, 3 iterations per
    tick, 256 ticks per segment, masked refresh, runs in their lane). On an accelerator: every
    slot of a device in one chunk, the slots from the device's memory (``ACCEL_MEMORY_SHARE``
    of it over ``slot_bytes`` (:func:`slot_bytes`, or a function giving it: called only on an
    accelerator) times ``ACCEL_TEMP_FACTOR``, a power of two
    from 256 to ``ACCEL_MAX_SLOTS``), 4 iterations per tick, 128 ticks per segment, the
    compacted refresh in groups of a quarter of the slots, runs to any free slot. With
    ``n_runs``, no more slots than the runs fill.
    """
    platform = platform or default_platform()
    overrides = {k: v for k, v in overrides.items() if v is not None}
    unknown = set(overrides) - {f.name for f in dataclasses.fields(EngineConfig)} - {"chosen"}
    if unknown:
        raise ValueError(f"unknown engine setting(s): {', '.join(sorted(unknown))}")
    notes = []
    if platform == "cpu":
        values = dict(CPU_DEFAULTS, refresh=CPU_REFRESH, assign="lane")
        notes.append("the CPU defaults, per device (measured on a 2-core x86-64 VM)")
    else:
        device = jax.local_devices(backend=platform)[0]
        memory = _device_memory(device)
        if "slots" in overrides:  # set by the user: nothing to size
            slot_bytes = None
        elif callable(slot_bytes):
            slot_bytes = slot_bytes()
        slots = accelerator_slots(memory, slot_bytes)
        if "slots" in overrides:
            notes.append(f"{device.device_kind}: {overrides['slots']} slots, as set")
        elif memory and slot_bytes:
            notes.append(
                f"{device.device_kind}: {memory / 2**30:.1f} GiB, {slot_bytes / 2**10:.0f} KiB "
                f"a slot x {ACCEL_TEMP_FACTOR} for a tick's temporaries -> {slots} slots a device"
            )
        else:
            notes.append(f"{device.device_kind}: memory or slot size unknown -> {slots} slots")
        values = dict(
            slots=slots,
            iterations=ACCEL_ITERATIONS,
            ticks_per_segment=ACCEL_TICKS,
            refresh="compacted",
            assign="any",
        )
        notes.append("accelerator settings not yet measured on a GPU")
    per_device = values["slots"]
    if n_runs is not None:
        need = max(1, math.ceil(n_runs / devices))
        chunk = overrides.get("chunk", values.get("chunk", 1))
        cap = max(256, 1 << (need - 1).bit_length()) if platform != "cpu" else need
        if values["assign"] == "lane":
            cap = chunk * math.ceil(need / chunk)
        if cap < per_device:
            per_device = cap
            notes.append(f"{n_runs} runs need {per_device} slots a device")
    values["slots"] = per_device * devices
    if platform != "cpu":
        values["chunk"] = per_device  # one chunk: every slot of a device in one kernel
    values.update(devices=devices, platform=platform)
    values.update(overrides)
    if platform != "cpu" and "chunk" not in overrides and "slots" in overrides:
        values["chunk"] = math.ceil(values["slots"] / devices)
    if values["assign"] == "lane":
        # whole chunks on every device: a run's lane (its bits) is its index mod the chunk
        # whatever the slots and devices
        per = values["chunk"] * math.ceil(math.ceil(values["slots"] / devices) / values["chunk"])
        values["slots"] = per * devices
    if values["refresh"] == "compacted" and values["assign"] == "any" and "group" not in overrides:
        values["group"] = max(1, values["chunk"] // ACCEL_REFRESH_SHARE)
    if overrides:
        notes.append("set: " + ", ".join(f"{k}={v}" for k, v in overrides.items()))
    return EngineConfig(**values, chosen="; ".join(notes))


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


def _resolve(loop, config, source: Source, params, sp, n_runs):
    if config is None:
        return auto_config(n_runs=n_runs, slot_bytes=lambda: slot_bytes(loop, source, params, sp))
    return config


class _Clock:
    """When each dispatched segment finished on the device (a watcher thread waits on it),
    for the device's busy time: from the dispatch's return (after any compile: host work) to
    the segment's end."""

    def __init__(self):
        self.pool = ThreadPoolExecutor(max_workers=1)
        self.pending = []
        self.busy = 0.0
        self.last_ready = 0.0

    def dispatched(self, t_dispatch: float, marker) -> None:
        def wait():
            jax.block_until_ready(marker)
            return time.perf_counter()

        self.pending.append((t_dispatch, self.pool.submit(wait)))

    def settle(self) -> None:
        for t_dispatch, fut in self.pending:
            ready = fut.result()
            self.busy += max(0.0, ready - max(t_dispatch, self.last_ready))
            self.last_ready = ready
        self.pending = []

    def close(self) -> None:
        self.settle()
        self.pool.shutdown()


def run_stream(
    loop: Loop,
    source_fn: Callable,
    blocks: Iterable[Block],
    n_runs: int,
    params=None,
    solver_params: SolverParams | None = None,
    config: EngineConfig | None = None,
    on_results: Callable | None = None,
    progress: Callable | None = None,
    keep: bool = True,
    deadline: float | None = None,
    lane_counts=None,
) -> dict:
    """Fly the ``n_runs`` runs of a queue given in blocks; the general form of
    :func:`run_batch`.

    Args:
        loop: the static closed loop (family + configuration).
        source_fn: ``fn(data, i) -> RunInputs`` (static, hashable).
        blocks: :class:`Block` s covering the queue's positions in order, each with data of
            the same shapes; the next is read when every run of the current one has been
            handed to a slot. With ``assign="lane"`` a block starts and ends on a multiple of
            the chunk (but the last).
        n_runs: number of runs in the queue.
        lane_counts: with ``assign="lane"``, (chunk,) the runs of each lane's queue: lane l
            flies queue positions l, C + l, 2 C + l, ... (C = chunk), ``lane_counts[l]`` of
            them (a queue with holes: positions past a lane's count are not runs). Default:
            positions 0 .. n_runs - 1.
        params: the family parameters shared by every run whose ``RunInputs.params`` is None.
        solver_params: shared solver parameters (default: the settings' defaults).
        config: :class:`EngineConfig` (None: :func:`auto_config` for the default device).
        on_results: called as ``on_results(positions, metrics)`` (NumPy) after every segment
            with the runs finished in it (e.g. to write them to disk as they come); the host
            work overlaps the device's next segment.
        progress: called as ``progress(done, n_runs)`` after every segment.
        keep: return every run's metrics (False: only the figures below; host memory then
            does not grow with the runs).
        deadline: ``time.perf_counter()`` value after which no further segment starts (the
            runs in flight are dropped, never reported).

    Returns:
        {"run": (n,) positions and "metrics" (with ``keep``), "done": runs finished,
        "ticks", "seconds" (wall time), "device_busy_s" (the device's time running segments),
        "compile_s" (the first dispatch: the compile, unless cached), "host_s" (the host's own
        work: collection and ``on_results``), "segments", "config"}.
    """
    if loop.config.settings.backend != "rvdjax":
        raise ValueError("the batch engine runs the rvdjax solver; use fly() for Clarabel")
    if n_runs < 1:
        raise ValueError(f"n_runs must be >= 1, got {n_runs}")
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    blocks = iter(blocks)
    block = next(blocks)
    if block.start != 0:
        raise ValueError("the first block of a queue starts at position 0")
    probe = jax.eval_shape(functools.partial(source_fn, block.data), jnp.asarray(0))
    if probe.params is None and params is None:
        raise ValueError("params must be given when the source gives no per-run parameters")
    cfg = _resolve(loop, config, Source(source_fn, block.data), params, sp, n_runs)
    if cfg.assign == "lane":
        C = cfg.chunk_size
        if lane_counts is None:
            lane_counts = np.maximum(0, -((np.arange(C) - n_runs) // C))
        lane_counts = np.asarray(lane_counts, np.int64)
        if lane_counts.shape != (C,) or lane_counts.sum() != n_runs:
            raise ValueError(f"lane_counts must hold {C} counts summing to n_runs = {n_runs}")
        end = int(lane_counts.max()) * C
    else:
        end = n_runs
    devices = _devices(cfg)
    D = len(devices)
    put = lambda tree: [jax.device_put(tree, dev) for dev in devices]  # noqa: E731
    t_setup = time.perf_counter()
    params_d, sp_d = put(params), put(sp)
    data = put(block.data)
    engs = _initial_state(loop, cfg, Source(source_fn, block.data), params, sp)
    segment = _build(loop, cfg, source_fn)
    pack = _compact_jit(cfg)
    ticks = jnp.asarray(cfg.ticks_per_segment, jnp.int32)
    upcoming = _next_block(blocks, block.stop, end, n_runs)
    collected_idx, collected = [], []
    done = 0
    host = 0.0
    segments = 0
    clock = _Clock()
    timing = {"compile_s": 0.0}
    t0 = time.perf_counter()
    on_cpu = devices[0].platform == "cpu"

    def dispatch(engs, block, upcoming):
        limit = jnp.asarray(_block_limit(cfg, block, lane_counts, n_runs))
        args = (jnp.asarray(block.start, jnp.int32), limit, jnp.asarray(upcoming is not None))
        called = time.perf_counter()
        out = [
            segment(e, data[d], *args, params_d[d], sp_d[d], ticks, jnp.int32(d), jnp.int32(D))
            for d, e in enumerate(engs)
        ]
        returned = time.perf_counter()
        first = not clock.pending and not clock.busy
        if first:  # the set-up and the first dispatch compile the programs
            timing["compile_s"] = returned - t_setup
        # The device's time starts at the call, not at its return. Timed from the return, the
        # busy share read 1e-4 on an H100: the call returned only when the segment was done,
        # most likely because XLA:GPU reads a while loop's condition back on the calling
        # thread (not yet confirmed with a profile).
        clock.dispatched(returned if first else called, [e.ticks for e in out])
        return out

    engs = dispatch(engs, block, upcoming)
    try:
        while True:
            segments += 1
            ring_done = [np.asarray(e.ring_done) for e in engs]  # waits for the segment
            th = time.perf_counter()
            found = [np.flatnonzero(r) for r in ring_done]
            gathered = [
                None
                if not len(pos)
                else (e.ring, e.ring_run, pos)  # NumPy reads a CPU device's arrays in place
                if on_cpu
                else _gather(_bucket(len(pos)))(e.ring, e.ring_run, _pad(pos, _bucket(len(pos))))
                for e, pos in zip(engs, found, strict=True)
            ]
            n_done = done + sum(len(p) for p in found)
            # the next segment: a new block once every run of this one is handed out
            next_seq = np.stack([np.asarray(e.next_seq) for e in engs])
            limit = _block_limit(cfg, block, lane_counts, n_runs)
            handed_out = _handed_out(cfg, next_seq, limit)
            if handed_out and upcoming is not None:
                block, upcoming = upcoming, _next_block(blocks, upcoming.stop, end, n_runs)
                data = put(block.data)
            if handed_out and upcoming is None and cfg.n_chunks > 1:
                engs = [pack(e) for e in engs]
            finished_all = n_done >= n_runs
            late = deadline is not None and time.perf_counter() > deadline
            if not finished_all and not late:
                engs = dispatch(engs, block, upcoming)
            host += time.perf_counter() - th
            th = time.perf_counter()
            for d, (pos, g) in enumerate(zip(found, gathered, strict=True)):
                if g is None:
                    continue
                if on_cpu:
                    res, seq = jax.tree.map(lambda a, pos=pos: np.asarray(a)[pos], g[:2])
                else:
                    n = len(pos)
                    res, seq = jax.tree.map(lambda a, n=n: np.asarray(a)[:n], g)
                positions = _positions(cfg, d, D, seq)
                if keep:
                    collected_idx.append(positions)
                    collected.append(res)
                if on_results is not None:
                    on_results(positions, res)
            host += time.perf_counter() - th
            done = n_done
            if progress is not None:
                progress(done, n_runs)
            if finished_all or late:
                break
    finally:
        clock.close()
    out = {
        "done": done,
        "ticks": max(int(e.ticks) for e in engs),
        "seconds": time.perf_counter() - t0,
        "device_busy_s": clock.busy,
        "compile_s": timing["compile_s"],
        "host_s": host,
        "segments": segments,
        "config": cfg,
    }
    if keep and collected:
        idx = np.concatenate(collected_idx)
        order = np.argsort(idx)
        out["run"] = idx[order]
        out["metrics"] = jax.tree.map(lambda *a: np.concatenate(a)[order], *collected)
    return out


def _bucket(n: int) -> int:
    """Gathers of 1, 2, 4, ... entries: few compiles."""
    return 1 << max(0, int(n - 1).bit_length())


def _pad(a, size: int):
    return np.concatenate([a, np.zeros(size - len(a), a.dtype)])


def _next_block(blocks: Iterator[Block], stop: int, end: int, n_runs: int) -> Block | None:
    if stop >= end:
        return None
    nxt = next(blocks, None)
    if nxt is None and stop >= n_runs:
        # the default lanes (run i in lane i mod chunk) leave every position past n_runs
        # empty: a queue of one block of n_runs entries is complete
        return None
    if nxt is None or nxt.start != stop:
        raise ValueError(f"the blocks of a queue must be contiguous: a block starting at {stop}")
    return nxt


def _handed_out(cfg: EngineConfig, next_seq, limit) -> bool:
    """Every run below ``limit`` has been handed to a slot (every device, every lane)."""
    D = next_seq.shape[0]
    return all(np.all(next_seq[d] >= _local_end(cfg, limit, d, D, np)) for d in range(D))


def run_batch(
    loop: Loop,
    source: Source,
    n_runs: int,
    params=None,
    solver_params: SolverParams | None = None,
    config: EngineConfig | None = None,
    on_results: Callable | None = None,
    progress: Callable | None = None,
) -> dict:
    """Fly ``n_runs`` runs through the engine's slots; return their metrics by run index.

    Args:
        loop: the static closed loop (family + configuration).
        source: a :class:`Source` (e.g. :func:`arrays_source`); run i is ``source.fn(data,
            i)``.
        n_runs: number of runs in the queue.
        params: the family parameters shared by every run whose ``RunInputs.params`` is None.
        solver_params: shared solver parameters (default: the settings' defaults).
        config: :class:`EngineConfig` (None: :func:`auto_config` for the default device).
        on_results: called as ``on_results(indices, metrics)`` (NumPy) after every segment
            with the runs finished in it (e.g. to write them to disk as they come).
        progress: called as ``progress(done, n_runs)`` after every segment.

    Returns:
        {"run": (n,) indices, "metrics": Metrics of NumPy arrays with a leading run axis in
        run-index order, "ticks", "seconds": wall time, and the figures of
        :func:`run_stream`}.
    """
    if not isinstance(source, Source):
        raise ValueError("source must be a rvdjax.loop.engine.Source (e.g. arrays_source(...))")
    return run_stream(
        loop,
        source.fn,
        [Block(source.data, 0, n_runs)],
        n_runs,
        params=params,
        solver_params=solver_params,
        config=config,
        on_results=on_results,
        progress=progress,
    )


def _abstract_args(loop, config: EngineConfig, source: Source, params, sp):
    """The segment's arguments as shapes."""
    eng = jax.eval_shape(lambda: _initial_state_one(loop, config.per_device, source, params, sp))
    scalar = lambda dtype: jax.ShapeDtypeStruct((), dtype)  # noqa: E731
    shape = lambda tree: jax.tree.map(  # noqa: E731
        lambda a: jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)), tree
    )
    return (
        eng,
        shape(source.data),
        scalar(jnp.int32),
        jax.ShapeDtypeStruct((config.lanes,), jnp.int32),
        scalar(jnp.bool_),
        shape(params),
        shape(sp),
        scalar(jnp.int32),
        scalar(jnp.int32),
        scalar(jnp.int32),
    )


def compile_engine(
    loop: Loop, source: Source, params=None, solver_params=None, config: EngineConfig | None = None
) -> float:
    """Compile the engine's programs for ``loop``, the queue's function and ``config`` without
    flying (a later :func:`run_batch` with the same shapes reuses them); returns XLA's planned
    memory of one device's segment program [MB]: arguments + outputs + temporaries, set by
    the slots and the ring, not by the number of runs in the queue."""
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    config = _resolve(loop, config, source, params, sp, None)
    device = _devices(config)[0]
    eng = _initial_state(loop, config, source, params, sp)[0]
    put = lambda tree: jax.device_put(tree, device)  # noqa: E731
    limit = jnp.ones(config.lanes, jnp.int32)
    compiled = (
        _build(loop, config, source.fn)
        .lower(
            eng,
            put(source.data),
            jnp.int32(0),
            limit,
            jnp.asarray(False),
            put(params),
            put(sp),
            jnp.asarray(config.ticks_per_segment, jnp.int32),
            jnp.int32(0),
            jnp.int32(config.devices),
        )
        .compile()
    )
    if config.n_chunks > 1:  # the packing of the live slots once the queue is empty
        _compact_jit(config).lower(eng).compile()
    try:
        m = compiled.memory_analysis()
        return (m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes) / 2**20
    except Exception:  # memory analysis is backend dependent
        return float("nan")


def export_segment(
    loop: Loop,
    source: Source,
    params=None,
    solver_params=None,
    config: EngineConfig | None = None,
    platforms=("cuda",),
):
    """Lower one device's segment program for ``platforms`` with ``jax.export`` (no device of
    that platform needed): a GPU lowering error shows up here on a CPU-only machine. Returns
    the :class:`jax.export.Exported`."""
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    if config is None:
        config = EngineConfig(slots=256, chunk=256, refresh="compacted", group=64, assign="any")
    program = segment_program(loop, config, source.fn)
    return jax.export.export(program, platforms=list(platforms))(
        *_abstract_args(loop, config, source, params, sp)
    )


def fly_batch(
    loop: Loop,
    params,
    x0s,
    keys=None,
    solver_params: SolverParams | None = None,
    config: EngineConfig | None = None,
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
