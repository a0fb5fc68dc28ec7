"""The batch engine's settings: :class:`EngineConfig` and :func:`auto_config` (the
defaults for the device), and the inputs of a run (:class:`RunInputs`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from rvdjax.devices import default_device
from rvdjax.solver import SolverParams


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
# Accelerators: one chunk of every slot (a kernel per operation for all slots), as many slots
# as memory allows up to ACCEL_MAX_SLOTS, the compacted refresh. Measured one at a time on one
# H200 (thesis-vbar, 2026-11-27, docs/benchmark.md): at 4 096 slots 8 iterations a tick flew
# 7 % slower, 2 iterations, 512 ticks a segment or the masked refresh within 4 %; the rate
# grew with the slots to about 1 800 maneuvers/s at 32 768 and stayed there at 65 536 (a
# solver iteration's memory traffic, not launches, bounds it there).
ACCEL_MAX_SLOTS = 65536
ACCEL_MEMORY_SHARE = 0.5  # of the device's memory for the engine (slots, ring, temporaries)
ACCEL_TEMP_FACTOR = 8  # temporaries of a tick per byte of slot state (Riccati factors, steps)
ACCEL_ITERATIONS = 4  # fewer ticks per solve: a tick's fixed cost is kernel launches
ACCEL_TICKS = 128
ACCEL_REFRESH_SHARE = 4  # a refresh group holds slots / 4 (about a third solve per tick)


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
        notes.append("the accelerator defaults (measured one by one on an H200)")
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
