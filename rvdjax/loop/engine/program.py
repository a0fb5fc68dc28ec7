"""The batch engine's compiled programs: one device's segment of ticks jitted once per loop,
configuration and queue function (:func:`segment_program`), and the compaction of the live
slots and the gather of ring entries between segments."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from rvdjax.loop.engine.config import EngineConfig
from rvdjax.loop.engine.device_programs import DevicePrograms
from rvdjax.loop.engine.segment import _segment
from rvdjax.loop.engine.slots import EngineState
from rvdjax.loop.kernel import Loop


def _build(loop: Loop, cfg: EngineConfig, source_fn):
    # the ticks per segment are an argument of the program, not part of it
    return _build_one(loop, dataclasses.replace(cfg.per_device, ticks_per_segment=1), source_fn)


@functools.lru_cache(maxsize=64)
def _build_one(loop: Loop, cfg: EngineConfig, source_fn):
    """The jitted segment function of one device (cached: one trace per loop, engine
    configuration of a device and queue function, whatever the data). Several devices run
    it each on its own slots and share of the queue, with no communication: the same
    program, and so the same bits as on one device. It is compiled once and loaded onto the
    further devices (:class:`~rvdjax.loop.engine.device_programs.DevicePrograms`), not
    compiled per device as ``jax.jit`` alone would.
    (A ``shard_map`` over the devices was partitioned by XLA:
    one of the solver's shared-model products took another layout, and the last bits of
    some runs differed from one device's.)"""
    return DevicePrograms(jax.jit(_segment(loop, cfg, source_fn)))


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
    return DevicePrograms(jax.jit(_compact(cfg.per_device)))


@functools.lru_cache(maxsize=64)
def _gather(size: int):
    """Pick ``size`` ring entries of one device's ring."""

    def take(ring, ring_run, pos):
        return jax.tree.map(lambda a: a[pos], ring), ring_run[pos]

    return jax.jit(take)
