"""The result every peer returns (:class:`PeerResult`) and the wrappers of the host solvers:
Clarabel, PIQP, DAQP (on the standard form and on the condensed problem) and OSQP, each called
from Python on a standard-form QP; listed in :data:`rvdjax.peers.PEERS`.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from rvdjax.qp import QP, qp_objective

__all__ = [
    "PeerResult",
    "solve_clarabel",
    "solve_piqp",
    "solve_daqp",
    "daqp_condensed_data",
    "solve_daqp_condensed",
    "solve_osqp",
]

# Tolerances of Clarabel's "reference" mode.
REFERENCE_TOL = 1e-10

# A solved QP's status as each peer spells it (Clarabel, PIQP, DAQP, OSQP, qpax, HPIPM).
SOLVED = ("Solved", "PIQP_SOLVED", "EXIT_OPTIMAL", "solved", "converged", "SUCCESS")


class PeerResult(NamedTuple):
    """Result of one peer solve.

    Attributes:
        z: (nz,) primal solution in the variables of the original QP.
        objective: 1/2 z'Pz + q'z + const, evaluated on the original QP.
        iterations: iterations reported by the solver.
        status: the solver's status string (a solved QP's: one of :data:`SOLVED`).
        solve_ms: wall-clock time of the solve call only [ms].
        setup_ms: wall-clock time of the solver set-up [ms].
    """

    z: np.ndarray
    objective: float
    iterations: int
    status: str
    solve_ms: float
    setup_ms: float


def _ms(t0: float) -> float:
    return 1e3 * (time.perf_counter() - t0)


def _n_eq_ineq(qp: QP) -> tuple[int, int]:
    return qp.A_eq.shape[0], qp.G.shape[0]


# --------------------------------------------------------------------------------------------
# Clarabel
# --------------------------------------------------------------------------------------------


def solve_clarabel(qp: QP, mode: str = "reference", **settings) -> PeerResult:
    """Solve with Clarabel (sparse interior point).

    Args:
        qp: the problem.
        mode: "reference" (gap/feasibility tolerances 1e-10) or "benchmark" (defaults).
        **settings: further ``clarabel.DefaultSettings`` attributes (override the mode).
    """
    import clarabel

    if mode not in ("reference", "benchmark"):
        raise ValueError(f"mode must be 'reference' or 'benchmark', got {mode!r}")
    t0 = time.perf_counter()
    n_eq, n_in = _n_eq_ineq(qp)
    P = sp.triu(qp.P).tocsc()
    A = sp.vstack([qp.A_eq, qp.G]).tocsc()
    b = np.concatenate([qp.b_eq, qp.h])
    cones = []
    if n_eq:
        cones.append(clarabel.ZeroConeT(n_eq))
    if n_in:
        cones.append(clarabel.NonnegativeConeT(n_in))
    s = clarabel.DefaultSettings()
    s.verbose = False
    s.max_threads = 1
    if mode == "reference":
        s.tol_gap_abs = s.tol_gap_rel = s.tol_feas = REFERENCE_TOL
        s.max_iter = 500
    for k, v in settings.items():
        if not hasattr(s, k):
            raise ValueError(f"unknown Clarabel setting {k!r}")
        setattr(s, k, v)
    solver = clarabel.DefaultSolver(P, np.asarray(qp.q, float), A, b, cones, s)
    setup_ms = _ms(t0)
    t0 = time.perf_counter()
    sol = solver.solve()
    solve_ms = _ms(t0)
    z = np.asarray(sol.x, dtype=float)
    return PeerResult(
        z, qp_objective(qp, z), int(sol.iterations), str(sol.status), solve_ms, setup_ms
    )


# --------------------------------------------------------------------------------------------
# PIQP
# --------------------------------------------------------------------------------------------


def solve_piqp(qp: QP, eps_abs: float = 1e-8, eps_rel: float = 1e-9, **settings) -> PeerResult:
    """Solve with PIQP's sparse solver (``G z <= h`` as upper-bounded rows ``h_u``)."""
    import piqp

    t0 = time.perf_counter()
    n_eq, n_in = _n_eq_ineq(qp)
    solver = piqp.SparseSolver()
    st = solver.settings
    st.verbose = False
    st.eps_abs = eps_abs
    st.eps_rel = eps_rel
    if hasattr(st, "num_threads"):
        st.num_threads = 1
    for k, v in settings.items():
        if not hasattr(st, k):
            raise ValueError(f"unknown PIQP setting {k!r}")
        setattr(st, k, v)
    # PIQP >= 0.6: setup(P, c, A, b, G, h_l, h_u, x_l, x_u); P full or upper triangular.
    solver.setup(
        sp.triu(qp.P).tocsc(),
        np.asarray(qp.q, float),
        qp.A_eq.tocsc() if n_eq else None,
        np.asarray(qp.b_eq, float) if n_eq else None,
        qp.G.tocsc() if n_in else None,
        None,
        np.asarray(qp.h, float) if n_in else None,
    )
    setup_ms = _ms(t0)
    t0 = time.perf_counter()
    status = solver.solve()
    solve_ms = _ms(t0)
    z = np.array(solver.result.x, dtype=float)
    status_str = getattr(status, "name", str(status))
    return PeerResult(
        z, qp_objective(qp, z), int(solver.result.info.iter), status_str, solve_ms, setup_ms
    )


# --------------------------------------------------------------------------------------------
# DAQP
# --------------------------------------------------------------------------------------------

_DAQP_EXIT = {
    1: "EXIT_OPTIMAL",
    2: "EXIT_SOFT_OPTIMAL",
    3: "EXIT_INFEASIBLE_BOUNDS",
    -1: "EXIT_INFEASIBLE",
    -2: "EXIT_CYCLE",
    -3: "EXIT_UNBOUNDED",
    -4: "EXIT_ITERLIMIT",
    -5: "EXIT_NONCONVEX",
    -6: "EXIT_OVERDETERMINED_INITIAL",
}


def solve_daqp(qp: QP, **settings) -> PeerResult:
    """Solve with DAQP (dense dual active set). Equalities via ``sense = 5``.

    ``daqp.solve`` is a one-shot call (set-up + solve): ``solve_ms`` times that call,
    ``setup_ms`` the dense conversion. DAQP's own split is not returned.
    """
    import daqp

    t0 = time.perf_counter()
    n_eq, n_in = _n_eq_ineq(qp)
    H = np.ascontiguousarray(qp.P.toarray(), dtype=np.float64)
    f = np.ascontiguousarray(qp.q, dtype=np.float64)
    A = np.ascontiguousarray(sp.vstack([qp.A_eq, qp.G]).toarray(), dtype=np.float64)
    bu = np.ascontiguousarray(np.concatenate([qp.b_eq, qp.h]), dtype=np.float64)
    bl = np.ascontiguousarray(np.concatenate([qp.b_eq, np.full(n_in, -1e30)]), dtype=np.float64)
    sense = np.concatenate([np.full(n_eq, 5, np.int32), np.zeros(n_in, np.int32)])
    setup_ms = _ms(t0)
    t0 = time.perf_counter()
    x, _fval, exitflag, info = daqp.solve(H, f, A, bu, bl, sense, **settings)
    solve_ms = _ms(t0)
    z = np.asarray(x, dtype=float)
    status = _DAQP_EXIT.get(int(exitflag), f"EXIT_{int(exitflag)}")
    return PeerResult(z, qp_objective(qp, z), int(info["iterations"]), status, solve_ms, setup_ms)


def daqp_condensed_data(c) -> tuple[np.ndarray, ...]:
    """(H, f, A, bupper, blower) of ``daqp.solve`` for a :class:`rvdjax.qp.CondensedQP`:
    the bounds on w first (DAQP reads the first ``nw`` entries of the bound vectors as bounds
    on the variables), then the general rows; 1e30 stands for "no bound"."""
    big = 1e30
    bu = np.concatenate([np.minimum(c.ub, big), c.h])
    bl = np.concatenate([np.maximum(c.lb, -big), np.full(c.h.size, -big)])
    H, f, A = (np.ascontiguousarray(a, dtype=np.float64) for a in (c.H, c.f, c.G))
    return H, f, A, bu, bl


def solve_daqp_condensed(qp: QP, **settings) -> PeerResult:
    """Solve with DAQP on the condensed problem (:func:`rvdjax.qp.condense`,
    :func:`daqp_condensed_data`); ``z`` mapped back to the standard form."""
    import daqp

    from rvdjax.qp import condense

    t0 = time.perf_counter()
    c = condense(qp)
    data = daqp_condensed_data(c)
    setup_ms = _ms(t0)
    t0 = time.perf_counter()
    w, _fval, exitflag, info = daqp.solve(*data, **settings)
    solve_ms = _ms(t0)
    z = c.Z @ np.asarray(w, dtype=float) + c.z0
    status = _DAQP_EXIT.get(int(exitflag), f"EXIT_{int(exitflag)}")
    return PeerResult(z, qp_objective(qp, z), int(info["iterations"]), status, solve_ms, setup_ms)


# --------------------------------------------------------------------------------------------
# OSQP
# --------------------------------------------------------------------------------------------


def solve_osqp(
    qp: QP, eps_abs: float = 1e-5, eps_rel: float = 1e-5, max_iter: int = 200_000, **settings
) -> PeerResult:
    """Solve with OSQP >= 1.0 (ADMM), ``l <= A z <= u``, equalities as ``l = u``; polishing on."""
    import osqp

    t0 = time.perf_counter()
    n_eq, n_in = _n_eq_ineq(qp)
    A = sp.vstack([qp.A_eq, qp.G]).tocsc()
    u = np.concatenate([qp.b_eq, qp.h])
    lo = np.concatenate([qp.b_eq, np.full(n_in, -np.inf)])
    opts = dict(verbose=False, polishing=True, eps_abs=eps_abs, eps_rel=eps_rel, max_iter=max_iter)
    opts.update(settings)
    solver = osqp.OSQP()
    solver.setup(sp.triu(qp.P).tocsc(), np.asarray(qp.q, float), A, lo, u, **opts)
    setup_ms = _ms(t0)
    t0 = time.perf_counter()
    res = solver.solve(raise_error=False)
    solve_ms = _ms(t0)
    z = np.asarray(res.x, dtype=float)
    status = str(res.info.status)
    return PeerResult(z, qp_objective(qp, z), int(res.info.iter), status, solve_ms, setup_ms)
