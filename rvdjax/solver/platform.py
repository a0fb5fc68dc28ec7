"""Which device a program is traced and lowered for, and the Newton step's form there: the
CUDA GPU's kernels or the CPU's XLA loops, chosen when a program is lowered for its device
(``lax.platform_dependent``)."""

from __future__ import annotations

import contextlib
import functools

import jax
from jax import lax

AUTO_ON_CUDA = "pallas-carried"  # what "auto" runs on a CUDA GPU (XLA's loops elsewhere)


def kernel_on(device, kernel: str = "auto") -> str:
    """The form of the Newton step ``kernel`` runs on ``device`` (a jax Device): "auto" is
    :data:`AUTO_ON_CUDA` on a CUDA GPU and "xla" elsewhere; any other form is itself."""
    if kernel != "auto":
        return kernel
    version = str(getattr(getattr(device, "client", None), "platform_version", "")).lower()
    cuda = device.platform in ("gpu", "cuda") and "rocm" not in version
    return AUTO_ON_CUDA if cuda else "xla"


_CUDA_TRACE = [None]  # None: from this process's backends; True: forced (tracing_for_cuda)


@functools.cache
def _process_has_gpu() -> bool:
    """Whether this process has a GPU backend (backends do not change once they are up)."""
    try:
        return bool(jax.devices("gpu"))
    except RuntimeError:  # no GPU backend (a CPU-only jaxlib, or no driver)
        return False


def traces_cuda() -> bool:
    """Whether programs traced now keep the CUDA form of the Newton step beside the CPU's (a
    process with a GPU, or inside :func:`tracing_for_cuda`)."""
    forced = _CUDA_TRACE[0]
    return _process_has_gpu() if forced is None else forced


@contextlib.contextmanager
def tracing_for_cuda():
    """Trace the Newton step's CUDA form (the GPU kernels) inside the block whatever devices
    this process has, so that a program traced here can be lowered for a CUDA GPU without one
    (``jax.export`` with ``platforms=["cuda"]``, ``lower(lowering_platforms=("cuda",))``, a
    compile for a described GPU).

    Outside it, a process without a GPU backend traces the CPU's form alone: the form is
    chosen by ``lax.platform_dependent``, which traces every branch, and tracing the kernels'
    entry-wise algebra for programs that can only run on the CPU took a fifth of the time of
    tests/test_paper_mode.py (43 s with it, 34 s without, 2026-11-28). A process with a GPU
    traces both forms, as before. Entering clears JAX's caches when the setting changes: a
    jitted function would otherwise reuse a trace that has only the CPU's form. (Traces made
    inside the block keep both forms; reused on the CPU afterwards, they lower its form.)"""
    old = _CUDA_TRACE[0]
    if not traces_cuda():
        jax.clear_caches()
    _CUDA_TRACE[0] = True
    try:
        yield
    finally:
        _CUDA_TRACE[0] = old


def cuda_or_default(*args, cuda, default):
    """``cuda(*args)`` where the program runs on a CUDA GPU, ``default(*args)`` elsewhere
    (``lax.platform_dependent``, decided when the program is lowered for its device); a
    process that cannot lower for a GPU traces ``default`` alone (:func:`tracing_for_cuda`)."""
    if not traces_cuda():
        return default(*args)
    return lax.platform_dependent(*args, cuda=cuda, default=default)
