"""Host backends: the same OCP solved by Clarabel (or a peer: PIQP, DAQP, HPIPM) on the host,
inside a jitted program.

``SolverSettings(backend="clarabel")`` routes every solve through ``jax.pure_callback``: the
reference "Clarabel in the loop" for any jitted closed loop (QP assembly in SciPy included).
``backend="piqp"`` (sparse interior point), ``backend="daqp"`` (dense active set on the
sparse-form QP) and ``backend="daqp-condensed"`` (the same on the condensed QP) are the peers
of the study benchmarks; ``backend="hpipm"`` flies HPIPM's OCP solver in the loop where its
library is installed (:mod:`rvdjax.peers_hpipm`). Not differentiable; a vmapped batch is
solved one problem at a time.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.ocp import OCP
from rvdjax.peers_host import SOLVED
from rvdjax.solver.types import Solution, Status

__all__ = ["solve_clarabel_backend"]


# a peer's options for one solve per MPC step (HPIPM's bench default solves twice and times
# the second: rvdjax.peers_hpipm.solve_hpipm)
_LOOP_OPTIONS = {"hpipm": {"resolve": False}}


def _host_solve(name: str, qp):
    from rvdjax import peers

    return peers.PEERS[name](qp, **_LOOP_OPTIONS.get(name, {}))


def _clarabel_host(*leaves, solver: str = "clarabel"):
    """Host side: one OCP as NumPy arrays -> (u, x, status, iterations)."""
    from rvdjax.qp import split_solution, to_qp

    ocp = OCP(*(np.asarray(a, dtype=np.float64) for a in leaves))
    N, nx, nu = ocp.B.shape
    dtype = np.asarray(leaves[0]).dtype
    try:
        res = _host_solve(solver, to_qp(ocp, soft=True))
        u, x = split_solution(res.z, N, nx, nu)
        ok = np.all(np.isfinite(u)) and np.all(np.isfinite(x))
        status = Status.CONVERGED if res.status in SOLVED else Status.MAX_ITER
        if "Infeasible" in res.status:
            status = Status.INFEASIBLE
        its = res.iterations
    except Exception:  # a failed host solve reports a status, never raises into the loop
        ok, status, its = False, Status.NONFINITE, 0
    if not ok:
        u, x, status = np.zeros((N, nu)), np.zeros((N, nx)), Status.NONFINITE
    return u.astype(dtype), x.astype(dtype), np.int32(status), np.int32(its)


def solve_clarabel_backend(ocp: OCP, solver: str = "clarabel") -> Solution:
    """Solve ``ocp`` with Clarabel (or a peer ``solver``: "piqp", "daqp", "daqp-condensed",
    "hpipm")
    through a host callback (objective filled in by the caller)."""
    dtype = ocp.B.dtype
    shapes = (
        jax.ShapeDtypeStruct((ocp.N, ocp.nu), dtype),
        jax.ShapeDtypeStruct((ocp.N, ocp.nx), dtype),
        jax.ShapeDtypeStruct((), jnp.int32),
        jax.ShapeDtypeStruct((), jnp.int32),
    )
    host = functools.partial(_clarabel_host, solver=solver)
    u, x, status, its = jax.pure_callback(host, shapes, *ocp, vmap_method="sequential")
    zero = jnp.zeros((), dtype)
    return Solution(u, x, jnp.zeros((ocp.N, ocp.nx), dtype), zero, zero, its, zero, status)
