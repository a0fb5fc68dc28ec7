"""A jitted one-device program compiled once and loaded onto every device that runs it.

``jax.jit`` keys its executables on the device, so a program run on D devices (the engine's
segment, each device on its own slots) is compiled D times: thesis-vbar's segment took 7.0,
12.9 and 30.4 s for 1, 2 and 4 host devices on the 2-core VM, and on a machine of several
GPUs each GPU compiles its own. The executable does not depend on which device of a platform
runs it, so :class:`DevicePrograms` compiles it for the first device and loads a copy of it
onto each further device (serialised and deserialised with that device's assignment, as
JAX's persistent cache shares one GPU program between devices): half a second for
thesis-vbar's segment on the 2-core VM, not another compile (15-19 s), and the same machine
code, so the same bits. Where loading fails (a JAX whose internals moved, a backend that
refuses), the device compiles its own, as ``jax.jit`` would.
"""

from __future__ import annotations

import io
import pickle
import threading

import jax
import numpy as np

from rvdjax.devices import default_device


def _key(args):
    """The call's argument signature (tree, shapes, dtypes, weak types) and its device: that
    of its committed arrays (the engine puts each device's state and data there), else the
    default device, where ``jax.jit`` would run it."""
    leaves, tree = jax.tree.flatten(args)
    device = None
    for leaf in leaves:
        if isinstance(leaf, jax.Array) and leaf.committed:
            devices = leaf.devices()
            if len(devices) == 1:
                device = next(iter(devices))
                break
    # (an array's aval, not jax.typeof: a third of the time on the engine's state)
    avals = tuple(x.aval if isinstance(x, jax.Array) else jax.typeof(x) for x in leaves)
    return (tree, avals), device or default_device()


class _OnDevice(pickle.Unpickler):
    """Reads what ``jax.experimental.serialize_executable.serialize`` wrote (a pickle whose
    persistent ids stand for the executable, its devices and its client) for ``device``:
    every device as ``device``, and the executable deserialised with ``device``'s assignment
    (the public ``deserialize_and_load`` keeps the source's, and the program would then
    refuse the device's buffers)."""

    def __init__(self, file, device):
        from jaxlib import xla_client

        super().__init__(file)
        self.device = device
        self.devices = xla_client.DeviceList((device,))
        self.options = xla_client.CompileOptions()
        self.options.num_replicas = self.options.num_partitions = 1
        self.options.device_assignment = xla_client.DeviceAssignment.create(np.array([[device.id]]))

    def persistent_load(self, pid):
        kind = pid[0]
        if kind == "exec":
            return self.device.client.deserialize_executable(pid[1], self.devices, self.options)
        if kind == "device":
            return self.device
        if kind == "client":
            return self.device.client
        raise pickle.UnpicklingError(f"unknown persistent id {kind!r}")


def load_on(compiled: jax.stages.Compiled, device) -> jax.stages.Compiled | None:
    """``compiled`` (a one-device program) loaded onto ``device`` of the same platform without
    compiling it again, or None where this JAX or backend cannot (the caller compiles)."""
    try:
        from jax.experimental import serialize_executable

        (source,) = compiled.runtime_executable().local_devices()
        if source == device:
            return compiled
        if source.platform != device.platform:
            return None
        payload, in_tree, out_tree = serialize_executable.serialize(compiled)
        unloaded, args_info, no_kwargs = _OnDevice(io.BytesIO(payload), device).load()
        return jax.stages.Compiled(
            unloaded.load(), [], in_tree.unflatten(args_info), out_tree, no_kwargs=no_kwargs
        )
    except Exception:  # JAX internals differ, or a host callback: compile on the device
        return None


class DevicePrograms:
    """``jitted`` run on the device of its arguments, compiled once per argument signature and
    loaded onto each further device (module docstring). Calls, ``lower`` and ``trace`` go
    through as to ``jitted``; :meth:`compiled` gives the device's executable (compiling or
    loading it ahead of a call, as the engine does before its first dispatch)."""

    def __init__(self, jitted):
        self.jitted = jitted
        self._executables: dict = {}
        self._lock = threading.Lock()
        self._loaded: set[int] = set()  # loaded executables not yet run
        self.compiles = 0  # executables compiled (the rest were loaded)

    def lower(self, *args, **kwargs):
        return self.jitted.lower(*args, **kwargs)

    def trace(self, *args, **kwargs):
        return self.jitted.trace(*args, **kwargs)

    def compiled(self, *args) -> jax.stages.Compiled:
        return self._executable(_key(args), args)

    def _executable(self, key, args) -> jax.stages.Compiled:
        with self._lock:
            exe = self._executables.get(key)
            if exe is not None:
                return exe
            source = next((e for (s, _), e in self._executables.items() if s == key[0]), None)
        exe = None if source is None else load_on(source, key[1])
        if exe is None:
            return self._compile(key, args)
        with self._lock:
            self._loaded.add(id(exe))
            return self._executables.setdefault(key, exe)

    def _compile(self, key, args) -> jax.stages.Compiled:
        # (threads that compile side by side each compile their own)
        exe = self.jitted.lower(*args).compile()
        with self._lock:
            self.compiles += 1
            self._executables[key] = exe
        return exe

    def __call__(self, *args):
        key = _key(args)
        exe = self._executable(key, args)
        if id(exe) not in self._loaded:
            return exe(*args)
        # A loaded program's first call proves it runs on the device (XLA checks the
        # buffers' devices against its assignment as it starts); should it refuse them, the
        # device compiles its own.
        try:
            out = exe(*args)
        except Exception:
            return self._compile(key, args)(*args)
        self._loaded.discard(id(exe))
        return out
