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

The modules: :mod:`.config` (the settings and their defaults per device), :mod:`.slots`
(the slots, the engine's state and the queue's inputs), :mod:`.segment` (the ticks of a
segment on a device), :mod:`.program` (the compiled programs), :mod:`.device_programs` (a
program compiled once and loaded onto every device) and :mod:`.stream` (the host's loop
around them).
"""

from __future__ import annotations

from rvdjax.loop.engine.config import (
    ACCEL_ITERATIONS,
    ACCEL_MAX_SLOTS,
    ACCEL_MEMORY_SHARE,
    ACCEL_REFRESH_SHARE,
    ACCEL_TEMP_FACTOR,
    ACCEL_TICKS,
    ASSIGN,
    CPU_DEFAULTS,
    CPU_REFRESH,
    REFRESH,
    EngineConfig,
    RunInputs,
    accelerator_slots,
    auto_config,
    default_platform,
)
from rvdjax.loop.engine.program import segment_program
from rvdjax.loop.engine.slots import (
    Block,
    EngineState,
    Slot,
    Source,
    arrays_source,
    slot_bytes,
)
from rvdjax.loop.engine.stream import (
    compile_engine,
    export_segment,
    fly_batch,
    run_batch,
    run_stream,
)

__all__ = [
    "RunInputs",
    "Source",
    "Block",
    "Slot",
    "EngineState",
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
    "REFRESH",
    "ASSIGN",
    "CPU_DEFAULTS",
    "CPU_REFRESH",
    "ACCEL_MAX_SLOTS",
    "ACCEL_MEMORY_SHARE",
    "ACCEL_TEMP_FACTOR",
    "ACCEL_ITERATIONS",
    "ACCEL_TICKS",
    "ACCEL_REFRESH_SHARE",
]
