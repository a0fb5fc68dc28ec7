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
- ``qpax`` (optional): interior point in JAX, dense. Its stopping test is an *absolute*
  ``||KKT residual||_inf < solver_tol`` and its iteration cap is small (30), so the raw RVD
  problems (slack costs rho ~ 1e6 next to P ~ 1) do not converge: :func:`solve_qpax` rescales
  the problem (Ruiz equilibration of the KKT matrix with q counted, then cost normalisation;
  see :func:`ruiz_scaling`) and maps the solution back. :func:`qpax_batch_solver` gives a
  jitted, vmapped solver over a batch of same-shape problems for batch timing.

Thread pinning: Clarabel (``max_threads = 1``) and PIQP (``num_threads = 1``) are pinned to one
thread; OSQP and DAQP are single-threaded; qpax runs on XLA, whose CPU thread pool is set at
process start (``XLA_FLAGS``), not per call.
"""

from __future__ import annotations

import functools
import importlib.util
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from rvdjax.qp import QP, qp_objective

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
    "solve_qpax",
    "qpax_batch_solver",
    "QpaxScaling",
    "ruiz_scaling",
]

# Tolerances of Clarabel's "reference" mode.
REFERENCE_TOL = 1e-10


class PeerResult(NamedTuple):
    """Result of one peer solve.

    Attributes:
        z: (nz,) primal solution in the variables of the original QP.
        objective: 1/2 z'Pz + q'z + const, evaluated on the original QP.
        iterations: iterations reported by the solver.
        status: the solver's status string (e.g. "Solved", "solved", "EXIT_OPTIMAL").
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


# --------------------------------------------------------------------------------------------
# qpax
# --------------------------------------------------------------------------------------------


class QpaxScaling(NamedTuple):
    """Diagonal scaling of a QP: z = D * zt; rows of A_eq by E, of G by F; cost by c."""

    D: np.ndarray
    E: np.ndarray
    F: np.ndarray
    c: float


def ruiz_scaling(
    P: np.ndarray,
    q: np.ndarray,
    A: np.ndarray,
    G: np.ndarray,
    iters: int = 30,
    bounds: tuple[float, float] = (1e-4, 1e4),
) -> QpaxScaling:
    """Ruiz equilibration of the KKT matrix [[P, A', G'], [A, 0, 0], [G, 0, 0]], with q as
    one more row, followed by one cost normalisation; dense matrices.

    The scaled problem is P~ = c D P D, q~ = c D q, A~ = E A D, b~ = E b, G~ = F G D,
    h~ = F h, and its solution maps back as z = D z~.

    Differs from OSQP's scheme (Stellato et al. 2020, Alg. 2), which normalises the cost inside
    the loop: with the L1 slacks' huge linear cost (rho ~ 1e6) that locks the cost scale c at
    its lower bound early and leaves P~ ~ 1e-4 (qpax then stops with objective errors ~1e-2).
    Counting |q| in the column norms instead drives the slack scale to D_s ~ 1/rho, so the
    scaled slack costs and the plan's P~ are both O(1) and qpax's absolute stopping test
    becomes meaningful in the original units. Per-iteration factors are clipped to ``bounds``.
    """
    lo, hi = bounds
    n = P.shape[0]
    C = np.vstack([A, G])
    D = np.ones(n)
    Er = np.ones(C.shape[0])
    Ps, Cs, qs = P.copy(), C.copy(), np.asarray(q, float).copy()
    for _ in range(iters):
        col = np.maximum.reduce(
            [np.abs(Ps).max(axis=0, initial=0.0), np.abs(Cs).max(axis=0, initial=0.0), np.abs(qs)]
        )
        row = np.abs(Cs).max(axis=1, initial=0.0)
        dD = 1.0 / np.sqrt(np.clip(np.where(col > 0, col, 1.0), lo, hi))
        dE = 1.0 / np.sqrt(np.clip(np.where(row > 0, row, 1.0), lo, hi))
        Ps = dD[:, None] * Ps * dD[None, :]
        Cs = dE[:, None] * Cs * dD[None, :]
        qs = dD * qs
        D *= dD
        Er *= dE
    gamma = max(
        float(np.mean(np.abs(Ps).max(axis=0, initial=0.0))), float(np.abs(qs).max(initial=0.0))
    )
    c = 1.0 / float(np.clip(gamma if gamma > 0 else 1.0, lo, hi))
    m = A.shape[0]
    return QpaxScaling(D, Er[:m], Er[m:], c)


def _qpax_dense(qp: QP, scale: bool):
    """Dense (possibly scaled) qpax data (Q, q, A, b, G, h) and the variable scaling D."""
    P = qp.P.toarray()
    q = np.asarray(qp.q, float)
    A = qp.A_eq.toarray()
    b = np.asarray(qp.b_eq, float)
    G = qp.G.toarray()
    h = np.asarray(qp.h, float)
    if not scale:
        return (P, q, A, b, G, h), np.ones(P.shape[0])
    s = ruiz_scaling(P, q, A, G)
    D, E, F, c = s
    data = (
        c * D[:, None] * P * D[None, :],
        c * D * q,
        E[:, None] * A * D[None, :],
        E * b,
        F[:, None] * G * D[None, :],
        F * h,
    )
    return data, D


@functools.lru_cache(maxsize=32)
def _qpax_jitted(solver_tol: float, max_iter: int, backend: str, kwargs: tuple, batched: bool):
    """Jitted (optionally vmapped) qpax solve, cached so repeated calls do not recompile."""
    import jax
    import qpax

    def solve(Q, q, A, b, G, h, D):
        x, _s, _z, _y, converged, iters = qpax.solve_qp(
            Q,
            q,
            A,
            b,
            G,
            h,
            backend=backend,
            solver_tol=solver_tol,
            max_iter=max_iter,
            **dict(kwargs),
        )
        return D * x, converged, iters

    return jax.jit(jax.vmap(solve) if batched else solve)


def solve_qpax(
    qp: QP,
    scale: bool = True,
    solver_tol: float = 1e-6,
    max_iter: int = 50,
    backend: str = "e",
    **kwargs,
) -> PeerResult:
    """Solve with qpax (dense primal-dual interior point in JAX, jitted).

    ``setup_ms`` is the densification and scaling plus a first call (which includes the jit
    compilation unless a problem of the same shape and settings was solved before in this
    process); ``solve_ms`` is a second call on the compiled function (``block_until_ready``).

    qpax's convergence test is absolute (``||KKT residual||_inf < solver_tol``, evaluated in
    the scaled problem), hence ``scale=True`` (:func:`ruiz_scaling`) by default; unscaled, the
    soft form (slack costs ~1e6) never converges. qpax floors its slacks and multipliers at
    sqrt(eps) ~ 1.5e-8 every iteration, so ``solver_tol`` below ~1e-7 is usually unreachable
    (status "not_converged" although the iterate is accurate). Status: "converged" or
    "not_converged". ``kwargs`` are forwarded to ``qpax.solve_qp`` (hashable values only).
    """
    import jax
    import jax.numpy as jnp

    t0 = time.perf_counter()
    data, D = _qpax_dense(qp, scale)
    args = tuple(jnp.asarray(a) for a in (*data, D))
    fn = _qpax_jitted(
        float(solver_tol), int(max_iter), backend, tuple(sorted(kwargs.items())), False
    )
    jax.block_until_ready(fn(*args))
    setup_ms = _ms(t0)
    t0 = time.perf_counter()
    x, converged, iters = jax.block_until_ready(fn(*args))
    solve_ms = _ms(t0)
    z = np.asarray(x, dtype=float)
    status = "converged" if int(converged) == 1 else "not_converged"
    return PeerResult(z, qp_objective(qp, z), int(iters), status, solve_ms, setup_ms)


class QpaxBatch:
    """A jitted, vmapped qpax solver bound to a stacked batch of dense problems.

    Attributes:
        fn: ``fn(Q, q, A, b, G, h, D) -> (z, converged, iters)``, jitted and vmapped over a
            leading batch axis; z is in the original variables (z = D * z~).
        data: the stacked (B, ...) arrays ``(Q, q, A, b, G, h, D)``.

    Calling the object runs ``fn(*data)`` (the first call compiles); time it with
    ``jax.block_until_ready(batch())``.
    """

    def __init__(self, fn: Callable, data: tuple):
        self.fn = fn
        self.data = data

    def __call__(self):
        return self.fn(*self.data)

    @property
    def batch_size(self) -> int:
        return int(self.data[0].shape[0])


def qpax_batch_solver(
    qp_list: list[QP],
    scale: bool = True,
    solver_tol: float = 1e-6,
    max_iter: int = 50,
    backend: str = "e",
    **kwargs,
) -> QpaxBatch:
    """Stack same-shape QPs as dense arrays and return a jitted+vmapped qpax solver.

    Each problem gets its own Ruiz scaling (``scale=True``); the returned ``z`` is mapped back.
    Raises ValueError if the problems' shapes differ.
    """
    import jax.numpy as jnp

    if not qp_list:
        raise ValueError("qp_list must contain at least one QP")
    shapes = {(q.P.shape, q.A_eq.shape, q.G.shape) for q in qp_list}
    if len(shapes) != 1:
        raise ValueError(f"all QPs must have the same shapes, got {sorted(shapes)}")
    per = [(*d, D) for d, D in (_qpax_dense(q, scale) for q in qp_list)]
    data = tuple(jnp.asarray(np.stack(a)) for a in zip(*per, strict=True))
    fn = _qpax_jitted(
        float(solver_tol), int(max_iter), backend, tuple(sorted(kwargs.items())), True
    )
    return QpaxBatch(fn, data)


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------

PEERS: dict[str, Callable[..., PeerResult]] = {
    "clarabel": solve_clarabel,
    "piqp": solve_piqp,
    "daqp": solve_daqp,
    "daqp-condensed": solve_daqp_condensed,
    "osqp": solve_osqp,
    "qpax": solve_qpax,
}


_MODULE = {"daqp-condensed": "daqp"}  # peer name -> the package it needs, where they differ


def available_peers() -> list[str]:
    """Names in :data:`PEERS` whose solver package is importable."""
    return [name for name in PEERS if importlib.util.find_spec(_MODULE.get(name, name)) is not None]
