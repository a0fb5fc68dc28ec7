"""The Clarabel backend: the same OCP solved by Clarabel on the host, inside a jitted program.

``SolverSettings(backend="clarabel")`` routes every solve through ``jax.pure_callback``: the
reference "Clarabel in the loop" for any jitted closed loop (QP assembly in SciPy included).
Not differentiable; a vmapped batch is solved one problem at a time.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.ocp import OCP
from rvdjax.solver.types import Solution, Status

__all__ = ["solve_clarabel_backend"]


def _clarabel_host(*leaves):
    """Host side: one OCP as NumPy arrays -> (u, x, status, iterations)."""
    from rvdjax.peers import solve_clarabel
    from rvdjax.qp import split_solution, to_qp

    ocp = OCP(*(np.asarray(a, dtype=np.float64) for a in leaves))
    N, nx, nu = ocp.B.shape
    dtype = np.asarray(leaves[0]).dtype
    try:
        res = solve_clarabel(to_qp(ocp, soft=True))
        u, x = split_solution(res.z, N, nx, nu)
        ok = np.all(np.isfinite(u)) and np.all(np.isfinite(x))
        status = Status.CONVERGED if res.status == "Solved" else Status.MAX_ITER
        if "Infeasible" in res.status:
            status = Status.INFEASIBLE
        its = res.iterations
    except Exception:  # a failed host solve reports a status, never raises into the loop
        ok, status, its = False, Status.NONFINITE, 0
    if not ok:
        u, x, status = np.zeros((N, nu)), np.zeros((N, nx)), Status.NONFINITE
    return u.astype(dtype), x.astype(dtype), np.int32(status), np.int32(its)


def solve_clarabel_backend(ocp: OCP) -> Solution:
    """Solve ``ocp`` with Clarabel through a host callback (objective filled in by the caller)."""
    dtype = ocp.B.dtype
    shapes = (
        jax.ShapeDtypeStruct((ocp.N, ocp.nu), dtype),
        jax.ShapeDtypeStruct((ocp.N, ocp.nx), dtype),
        jax.ShapeDtypeStruct((), jnp.int32),
        jax.ShapeDtypeStruct((), jnp.int32),
    )
    u, x, status, its = jax.pure_callback(_clarabel_host, shapes, *ocp, vmap_method="sequential")
    zero = jnp.zeros((), dtype)
    return Solution(u, x, jnp.zeros((ocp.N, ocp.nx), dtype), zero, zero, its, zero, status)
