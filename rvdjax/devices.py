"""Which device a piece of work runs on: the CPU or a GPU, chosen by the kind of work.

One maneuver is a chain of small dependent solves: on a GPU each solver iteration is a
string of kernel launches and device syncs, so one maneuver flies slower there than on the
same machine's CPU (measured on one H100 with 16 CPU cores, jax 0.11.2, float64:
``rvdjax run fastmpc-3d`` took 14.2 ms an MPC step on the GPU, 0.37 ms on the CPU;
docs/benchmark.md). A batch of thousands of maneuvers fills the GPU. So ``"auto"`` places
single-maneuver work (run, compare, tune, demo) on the CPU and batch work (studies,
verification, the GPU benchmark) on JAX's default device, a GPU where there is one. A user
overrides either with ``--device cpu|gpu``.
"""

from __future__ import annotations

import contextlib
from typing import Literal

__all__ = ["CHOICES", "WORK", "current", "default_device", "describe", "placed", "resolve"]

CHOICES = ("auto", "cpu", "gpu")
WORK = ("single", "batch")


def _platform_devices(platform: str):
    import jax

    try:  # this process's devices (under jax.distributed, jax.devices() lists every host's)
        return jax.local_devices(backend=platform)
    except RuntimeError:  # JAX raises RuntimeError for a backend it does not have
        return []


def resolve(choice: str = "auto", work: Literal["single", "batch"] = "single"):
    """The ``jax.Device`` for ``work`` ("single": one maneuver at a time, "batch": many).

    Args:
        choice: "auto" (single work on the CPU, batch work on JAX's default device), "cpu"
            or "gpu".

    Raises:
        ValueError: an unknown choice, or "gpu" where JAX sees no GPU (checked before any
            work, so a command stops at once with one line).
    """
    import jax

    if choice not in CHOICES:
        raise ValueError(f"--device must be one of {', '.join(CHOICES)}, got {choice!r}")
    if work not in WORK:
        raise ValueError(f"work must be one of {WORK}, got {work!r}")
    if choice == "gpu":
        gpus = _platform_devices("gpu")
        if not gpus:
            seen = sorted({d.platform for d in jax.devices()})
            raise ValueError(
                "--device gpu: JAX sees no GPU here (devices: "
                f"{', '.join(seen)}); install a CUDA build of jax, e.g. "
                "pip install 'jax[cuda12]', or use --device cpu"
            )
        return gpus[0]
    if choice == "cpu" or work == "single":
        return _platform_devices("cpu")[0]
    return jax.local_devices()[0]


def describe(device) -> str:
    """A short name of a device for outputs and tables: "cpu" or "gpu (NVIDIA H100 ...)"."""
    platform = "gpu" if device.platform in ("gpu", "cuda", "rocm") else device.platform
    kind = getattr(device, "device_kind", "") or ""
    if platform == "cpu" or not kind:
        return platform
    return f"{platform} ({kind})"


def default_device():
    """The device JAX places work on now: ``jax.default_device`` when set (inside
    :func:`placed`, by ``--device``), else this process's first device."""
    import jax

    device = jax.config.jax_default_device
    if isinstance(device, str):  # a platform name
        return _platform_devices(device)[0]
    return device if device is not None else jax.local_devices()[0]


def current() -> str:
    """:func:`describe` of :func:`default_device`."""
    return describe(default_device())


@contextlib.contextmanager
def placed(choice: str = "auto", work: Literal["single", "batch"] = "single"):
    """Run the block's JAX work on :func:`resolve`'s device; yields the device."""
    import jax

    device = resolve(choice, work)
    with jax.default_device(device):
        yield device
