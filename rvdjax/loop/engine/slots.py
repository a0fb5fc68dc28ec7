"""The batch engine's state on a device: the slots (:class:`Slot`), the engine's state
(:class:`EngineState`) and the queue's inputs (:class:`Source`, :class:`Block`), built empty
for each device and sized from shapes (:func:`slot_bytes`)."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from rvdjax.loop.engine.config import EngineConfig, RunInputs, default_platform
from rvdjax.loop.kernel import (
    Loop,
    LoopState,
    Metrics,
    init,
    metrics,
    prepare,
)
from rvdjax.ocp import OCP
from rvdjax.solver import SolverParams, SolveState, freeze, start
from rvdjax.solver.barrier import rows_of
from rvdjax.solver.driver import MODEL_FIELDS
from rvdjax.solver.platform import traces_cuda
from rvdjax.solver.riccati import ModelTable


def probe_run(source_fn, data):
    """The shapes of a run the source gives (its index given as a shape: nothing is
    computed, so nothing compiles)."""
    index = jax.ShapeDtypeStruct((), jnp.result_type(int), weak_type=True)
    return jax.eval_shape(functools.partial(source_fn, data), index)


def slot_bytes(loop: Loop, source: Source, params=None, solver_params=None) -> int:
    """Bytes of one slot's state for this loop and queue (from shapes only: nothing is
    compiled or run)."""
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    probe = probe_run(source.fn, source.data)
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


#: The OCP fields besides the model's (A, B, c, Q, R) that a family's ``model`` hook may
#: rebuild: the linear costs, the hard input rows (Fu and fu together; their mask stays in
#: the slot, which neutralises the masked rows as the solver's start does) and the state rows'
#: mask and penalty (together, the penalty neutralised where the mask is off; the rows
#: themselves, Fx and fx, stay in the slot as the start neutralised them).
ROWS_REBUILT = ("q", "r", "Fu", "fu", "x_mask", "rho")


def model_of(loop: Loop, params, guidance) -> dict | None:
    """The OCP fields that the family rebuilds from its parameters and a slot's guidance state
    instead of storing them in every slot (its ``model`` hook: (A, B, c, Q, R), or a dict of
    those and any of :data:`ROWS_REBUILT`, and optionally ``table``, a function returning a
    :class:`~rvdjax.solver.riccati.ModelTable` whose entry is the slot's [B, A]), or None (all
    stored). Computed inside the slots' ``vmap``, they stay unbatched where they depend on
    neither (one model and one input box for the batch); the three-phase family's depend on
    the phase, a few small tables gathered by each fusion that reads them instead of 31 KB a
    slot read from device memory, and by the GPU kernels from the table (:func:`table_of`)."""
    if loop.family.model is None:
        return None
    fields = loop.family.model(params, loop.config.family_config, guidance)
    if fields is None:
        return None
    if not isinstance(fields, dict):
        return dict(zip(MODEL_FIELDS, fields, strict=True))
    names = set(fields)
    if (
        names - set(MODEL_FIELDS) - set(ROWS_REBUILT) - {"table"}
        or not set(MODEL_FIELDS) <= names
        or len({"Fu", "fu"} & names) == 1
        or len({"x_mask", "rho"} & names) == 1
    ):
        raise TypeError(
            f"{loop.family.name}: model must return (A, B, c, Q, R) or a dict of those and "
            f"any of q, r, the input rows (Fu and fu together) and the state rows' mask and "
            f"penalty (x_mask and rho together), and a model table, got {sorted(names)}"
        )
    return fields


def table_of(model) -> ModelTable | None:
    """The model table of a family's rebuilt fields (:func:`model_of`) where the program
    traced now has the GPU kernels that read it (:func:`rvdjax.solver.platform.traces_cuda`),
    else None: a CPU-only process's programs are the same with or without a table, and
    without one they carry no unused tables through their loops."""
    table = None if model is None else model.get("table")
    return None if table is None or not traces_cuda() else ModelTable(*table())


def _fields(model) -> dict:
    return {k: v for k, v in model.items() if k != "table"}


def _strip_model(ocp: OCP, model) -> OCP:
    """The OCP without the fields a family rebuilds (:func:`model_of`), stored per slot."""
    if model is None:
        return ocp
    return ocp._replace(**{k: jnp.zeros((), ocp.B.dtype) for k in _fields(model)})


def _with_model(ocp: OCP, model) -> OCP:
    """The slot's OCP with the fields its family rebuilds: the input rows neutralised where
    the slot's mask is off (zero row, offset 1), as :func:`rvdjax.solver.start` neutralised
    the rows it iterates on (``barrier.rows_of``)."""
    if model is None:
        return ocp
    ocp = ocp._replace(**_fields(model))
    if "Fu" in model:
        rows = rows_of(ocp)
        ocp = ocp._replace(Fu=rows.Fu, fu=rows.fu)
    return ocp


def _empty_slot(loop: Loop, params, sp, source, per_run_params, per_run_solver) -> Slot:
    """A free slot with the right shapes (built from the queue's first entry, then marked
    free)."""
    run = source(jnp.asarray(0))
    p = run.params if per_run_params else params
    s = run.solver if per_run_solver else sp
    state = init(loop, p, run.x0, run.key)
    prep = prepare(loop, p, state)
    model = model_of(loop, p, prep.guidance)
    ocp, solve_state = start(
        prep.ocp,
        loop.config.settings,
        s,
        prep.warm,
        trusted_model=model is not None,
        in_kernels=False,  # formed at each tick (segment._iterate_chunk)
    )
    ocp = _strip_model(ocp, model)
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


@functools.lru_cache(maxsize=64)
def _state_builder(
    loop: Loop, source_fn, per_run_params: bool, per_run_solver: bool, B: int, R: int, lanes: int
):
    """The engine's state of ``B`` empty slots and a ring of ``R`` as one program (built
    eagerly, each slot and ring leaf's broadcast was a program of its own, compiled on its
    first use: 25 of a study's start)."""

    def build(data, params, sp):
        src = functools.partial(source_fn, data)
        slot = _empty_slot(loop, params, sp, src, per_run_params, per_run_solver)
        ring0 = metrics(loop, slot.params if per_run_params else params, slot.state)
        # strong types: the segment's outputs must have exactly the types of its inputs, or
        # every segment after the first would trace and compile again
        slot = jax.tree.map(lambda a: jnp.asarray(a, dtype=a.dtype), slot)
        return EngineState(
            slots=jax.tree.map(lambda a: jnp.broadcast_to(a, (B, *a.shape)), slot),
            next_seq=jnp.arange(lanes, dtype=jnp.int32),
            ring_run=jnp.full(R, -1, jnp.int32),
            ring_done=jnp.zeros(R, bool),
            ring=jax.tree.map(lambda a: jnp.zeros((R, *a.shape), a.dtype), ring0),
            ticks=jnp.asarray(0, jnp.int32),
            stalled=jnp.asarray(False),
        )

    return jax.jit(build)


def _initial_state(loop, config: EngineConfig, source: Source, params, sp) -> list:
    """One engine state per device (on it)."""
    one = _initial_state_one(loop, config.per_device, source, params, sp)
    return [jax.device_put(one, d) for d in _devices(config)]


def _initial_state_one(loop, config: EngineConfig, source: Source, params, sp):
    probe = probe_run(source.fn, source.data)
    build = _state_builder(
        loop,
        source.fn,
        probe.params is not None,
        probe.solver is not None,
        config.n_slots,
        config.ring_size,
        config.lanes,
    )
    return build(source.data, params, sp)
