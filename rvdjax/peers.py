"""Uniform wrappers around reference and peer QP solvers.

Every wrapper takes a standard-form :class:`~rvdjax.qp.QP`::

    minimise 1/2 z^T P z + q^T z + const   s.t.   A_eq z = b_eq,   G z <= h

and returns a :class:`PeerResult`. ``objective`` is always recomputed from ``z`` on the
original problem (including ``qp.const``), so the peers are compared on the same footing
whatever their internal scaling or objective convention. ``setup_ms`` covers building the
solver (matrix conversion, factorisation set-up, jit compilation for qpax); ``solve_ms`` is the
wall-clock time (``time.perf_counter``) of the solve call only.

Solvers (``PEERS`` registry; :func:`available_peers` lists the importable ones):

- ``clarabel`` (required dependency): interior point, sparse. ``mode="reference"`` tightens
  the gap and feasibility tolerances to 1e-10 (the ground truth of the tests);
  ``mode="benchmark"`` keeps Clarabel's defaults (1e-8).
- ``piqp`` (optional): proximal interior point, sparse (``piqp.SparseSolver``).
- ``daqp`` (optional): dual active set, dense. Needs H positive definite: the plan block of P
  is (R, Q > 0 on the inputs and states), but the slack block of the soft form is zero. DAQP's
  default automatic proximal regularisation (``eps_prox < 0``) handles that; pass the hard
  form (``to_qp(ocp, soft=False)``) for a strict comparison.
- ``daqp-condensed`` (optional): DAQP on the condensed problem (:func:`rvdjax.qp.condense`:
  the states eliminated through the dynamics, w = (u, s) dense, thrust boxes and s >= 0 as
  DAQP's simple bounds), the form a dense active-set solver is meant for in MPC. Solved cold;
  ``setup_ms`` is the condensing.
- ``osqp`` (optional): ADMM, sparse, ``l <= A z <= u`` with ``l = u`` on the equality rows,
  solution polishing on, ``eps_abs = eps_rel = 1e-5``. Only accurate to ~1e-5.
- ``hpipm`` (optional, :mod:`rvdjax.peers_hpipm`): HPIPM's interior point on the OCP structure
  (Riccati recursion, BLASFEO's kernels), the solver acados runs; its library is found from
  ``RVDJAX_HPIPM_LIB`` or an importable ``acados`` package, where this CPU has what it was
  built for. Solved from the drift of x0 (zero inputs and the states they give: the start of
  rvdjax's own cold solve), in its ``balance`` mode with mu0 the largest of 1e5 and the
  soft rows' penalties, to 1e-8.
- ``qpax`` (optional): interior point in JAX, dense. Its stopping test is an *absolute*
  ``||KKT residual||_inf < solver_tol`` and its iteration cap is small (30), so the raw RVD
  problems (slack costs rho ~ 1e6 next to P ~ 1) do not converge: :func:`solve_qpax` rescales
  the problem (Ruiz equilibration of the KKT matrix with q counted, then cost normalisation;
  see :func:`ruiz_scaling`) and maps the solution back. :func:`qpax_batch_solver` gives a
  jitted, vmapped solver over a batch of same-shape problems for batch timing.

Thread pinning: Clarabel (``max_threads = 1``) and PIQP (``num_threads = 1``) are pinned to one
thread; OSQP, DAQP and HPIPM are single-threaded; qpax runs on XLA, whose CPU thread pool is set at
process start (``XLA_FLAGS``), not per call.

The wrappers are in :mod:`rvdjax.peers_host` (:class:`PeerResult`, Clarabel, PIQP, DAQP, OSQP)
and :mod:`rvdjax.peers_qpax` (qpax); this module holds the registry and re-exports them.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable

from rvdjax.peers_host import (
    REFERENCE_TOL,  # noqa: F401  (re-exported)
    PeerResult,
    daqp_condensed_data,
    solve_clarabel,
    solve_daqp,
    solve_daqp_condensed,
    solve_osqp,
    solve_piqp,
)
from rvdjax.peers_hpipm import hpipm_library, hpipm_unavailable, solve_hpipm
from rvdjax.peers_qpax import (
    QpaxBatch,  # noqa: F401  (re-exported)
    QpaxScaling,
    qpax_batch_solver,
    ruiz_scaling,
    solve_qpax,
)

__all__ = [
    "PeerResult",
    "PEERS",
    "available_peers",
    "solve_clarabel",
    "solve_piqp",
    "solve_daqp",
    "solve_daqp_condensed",
    "daqp_condensed_data",
    "solve_osqp",
    "solve_hpipm",
    "hpipm_library",
    "hpipm_unavailable",
    "solve_qpax",
    "qpax_batch_solver",
    "QpaxScaling",
    "ruiz_scaling",
]

# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------

PEERS: dict[str, Callable[..., PeerResult]] = {
    "clarabel": solve_clarabel,
    "piqp": solve_piqp,
    "daqp": solve_daqp,
    "daqp-condensed": solve_daqp_condensed,
    "osqp": solve_osqp,
    "hpipm": solve_hpipm,
    "qpax": solve_qpax,
}


_MODULE = {"daqp-condensed": "daqp"}  # peer name -> the package it needs, where they differ


def _available(name: str) -> bool:
    if name == "hpipm":  # a shared library, not a package (rvdjax.peers_hpipm)
        return hpipm_library() is not None
    return importlib.util.find_spec(_MODULE.get(name, name)) is not None


def available_peers() -> list[str]:
    """Names in :data:`PEERS` whose solver is usable here (its package importable; HPIPM's
    library found and built for this CPU)."""
    return [name for name in PEERS if _available(name)]
