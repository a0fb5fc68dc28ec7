"""The batch engine on the host: segments dispatched, results collected between them, blocks
of the queue fed in (:func:`run_stream`, :func:`run_batch`, :func:`fly_batch`), and the
programs compiled or exported ahead of a run."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.batching import shapes_of
from rvdjax.loop.engine.config import EngineConfig, auto_config
from rvdjax.loop.engine.program import _build, _compact_jit, _gather, segment_program
from rvdjax.loop.engine.segment import _block_limit, _local_end, _positions
from rvdjax.loop.engine.slots import (
    Block,
    Source,
    _devices,
    _initial_state,
    _initial_state_one,
    arrays_source,
    probe_run,
    slot_bytes,
)
from rvdjax.loop.kernel import (
    Loop,
    Metrics,
)
from rvdjax.solver import SolverParams, tracing_for_cuda


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
        "compile_s" (the set-up and the compile before the first dispatch), "host_s" (the host's own
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
    probe = probe_run(source_fn, block.data)
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

    def dispatch(engs, block, upcoming, first=False):
        limit = jnp.asarray(_block_limit(cfg, block, lane_counts, n_runs))
        args = (jnp.asarray(block.start, jnp.int32), limit, jnp.asarray(upcoming is not None))
        per_device = [
            (e, data[d], *args, params_d[d], sp_d[d], ticks, jnp.int32(d), jnp.int32(D))
            for d, e in enumerate(engs)
        ]
        if first:  # the programs compiled before the first call
            compile_side_by_side(segment, per_device, pack if cfg.n_chunks > 1 else None)
            timing["compile_s"] = time.perf_counter() - t_setup
        # The device's time starts at the call, not at its return: on a GPU the call returns
        # only when the segment is done (the busy share read 1e-4 on an H100 timed from the
        # return), most likely because XLA:GPU reads a while loop's condition back on the
        # calling thread. So the programs are compiled before the first call and every call
        # is timed from its start. (The first call used to compile too and was timed from its
        # return, so its segment counted as nobody's time: on an H200, 2026-11-27,
        # thesis-vbar's busy share read 0.45 with 512 ticks a segment against 0.82 with 128.)
        called = time.perf_counter()
        out = [segment(*a) for a in per_device]
        clock.dispatched(called, [e.ticks for e in out])
        return out

    engs = dispatch(engs, block, upcoming, first=True)
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


def compile_threads(devices: int, cores: int | None = None) -> int:
    """Threads that compile the devices' programs side by side where a device cannot load the
    first device's program (:func:`compile_side_by_side`): one per device, at most half the
    host's cores (``cores``: those this process may run on), since one XLA compile of
    thesis-vbar's segment already keeps 1.5 of the 2-core VM's cores busy (11.1 s of CPU in
    7.4 s). 1: one device after another."""
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(devices, (cores or 1) // 2))


def compile_side_by_side(segment, per_device, pack=None, threads: int | None = None) -> int:
    """Make the segment program (and the packing program) of every device before the first
    dispatch: compiled for the first device and loaded onto the others
    (:class:`~rvdjax.loop.engine.device_programs.DevicePrograms`: thesis-vbar's segment took
    7.0, 12.9 and 30.4 s to compile for 1, 2 and 4 host devices on the 2-core VM, one compile
    per device, before the devices loaded the first one's). A device that cannot load it
    compiles its own, :func:`compile_threads` at a time (XLA compiles without the interpreter
    lock). Returns the threads used (1: one device after another). The later calls find these
    executables: the same program, so the same bits, and no compile inside a call (whose time
    the engine counts as the device's)."""
    threads = compile_threads(len(per_device)) if threads is None else threads

    def one(args):
        segment.compiled(*args)
        if pack is not None:
            pack.compiled(args[0])

    one(per_device[0])
    if threads <= 1:
        for args in per_device[1:]:
            one(args)
        return 1
    with ThreadPoolExecutor(max_workers=threads) as pool:
        list(pool.map(one, per_device[1:]))
    return threads


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
    return (
        eng,
        shapes_of(source.data),
        scalar(jnp.int32),
        jax.ShapeDtypeStruct((config.lanes,), jnp.int32),
        scalar(jnp.bool_),
        shapes_of(params),
        shapes_of(sp),
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
    compiled = _compile_segment(loop, source, params, solver_params, config)
    try:
        m = compiled.memory_analysis()
        return (m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes) / 2**20
    except Exception:  # memory analysis is backend dependent
        return float("nan")


def _compile_segment(loop, source, params, solver_params, config):
    """:func:`compile_engine`'s work: the compiled segment program of one device (the packing
    program too when there are several chunks), the one a later flight reuses."""
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    config = _resolve(loop, config, source, params, sp, None)
    device = _devices(config)[0]
    eng = _initial_state(loop, config, source, params, sp)[0]
    put = lambda tree: jax.device_put(tree, device)  # noqa: E731
    limit = jnp.ones(config.lanes, jnp.int32)
    compiled = _build(loop, config, source.fn).compiled(
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
    if config.n_chunks > 1:  # the packing of the live slots once the queue is empty
        _compact_jit(config).compiled(eng)
    return compiled


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
    if config is None:  # the accelerator settings, for the first platform
        config = EngineConfig(
            slots=256,
            chunk=256,
            refresh="compacted",
            group=64,
            assign="any",
            platform=platforms[0],
        )
    program = segment_program(loop, config, source.fn)
    # The solver's Pallas kernels (the default on a CUDA GPU) are Triton custom calls, which
    # jax.export refuses by default because their serialised form is not kept compatible
    # across jax versions; this export checks the lowering and is never stored.
    triton = jax.export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")
    exporter = jax.export.export(program, platforms=list(platforms), disabled_checks=[triton])
    with tracing_for_cuda() if "cuda" in platforms else contextlib.nullcontext():
        return exporter(*_abstract_args(loop, config, source, params, sp))


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
