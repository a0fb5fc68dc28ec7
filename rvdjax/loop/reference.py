"""The reference loop: the kernel's own ``step``, driven MPC step by MPC step from Python with
Clarabel solving every QP (``SolverSettings(backend="clarabel")``).

Used to check that rvdjax flies the same trajectory as an independent QP solver, and as the
"one by one from a Python loop" baseline of the benchmarks: every step is one call of the
jitted step (a host callback inside it runs Clarabel on the step's OCP, QP assembly in SciPy
included).
"""

from __future__ import annotations

import functools
import time

import jax
import numpy as np

from rvdjax.loop.kernel import Loop, fly, init, metrics, step
from rvdjax.solver import SolverParams, SolverSettings

__all__ = ["reference_loop", "clarabel_loop"]


def clarabel_loop(loop: Loop, backend: str = "clarabel") -> Loop:
    """The same loop with Clarabel (or the peer ``backend``: "piqp", "daqp",
    "daqp-condensed") as the solver."""
    return loop.replace(settings=SolverSettings(backend=backend))


@functools.lru_cache(maxsize=32)
def _jitted_step(loop: Loop):
    return jax.jit(lambda p, sp, s: step(loop, p, sp, s))


@functools.lru_cache(maxsize=32)
def _jitted_init(loop: Loop):
    return jax.jit(lambda p, x, k: init(loop, p, x, k))


def reference_loop(
    loop: Loop, params, x0, key=None, stop_when_done: bool = True, backend: str = "clarabel"
):
    """Fly one maneuver step by step from Python with Clarabel.

    Args:
        loop: the closed loop (its solver settings are replaced by the Clarabel backend).
        params, x0, key: as :func:`rvdjax.loop.fly`.
        stop_when_done: stop calling the step once the run has finished (the idle steps of
            ``fly`` are not flown).
        backend: the host solver, "clarabel" (default), "piqp", "daqp" or "daqp-condensed".

    Returns:
        (list of per-step :class:`~rvdjax.loop.StepInfo` (NumPy), Metrics (NumPy), seconds).
    """
    ref = clarabel_loop(loop, backend)
    sp = SolverParams.for_settings(ref.config.settings)
    step_fn = _jitted_step(ref)
    state = _jitted_init(ref)(params, x0, jax.random.key(0) if key is None else key)
    infos = []
    t0 = time.perf_counter()
    for _ in range(ref.config.n_steps):
        if stop_when_done and not bool(state.active):
            break
        state, info = step_fn(params, sp, state)
        infos.append(jax.tree.map(np.asarray, info))
    seconds = time.perf_counter() - t0
    return infos, jax.tree.map(np.asarray, metrics(ref, params, state)), seconds


def fly_clarabel(loop: Loop, params, x0, key=None):
    """The whole maneuver jitted, with Clarabel in the loop (a host callback per step)."""
    return fly(clarabel_loop(loop), params, x0, key)
