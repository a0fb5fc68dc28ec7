"""qpax, the peer in JAX: Ruiz equilibration of the dense problem (:func:`ruiz_scaling`), the
jitted solve of one problem (:func:`solve_qpax`) and a jitted, vmapped solver over a batch of
same-shape problems (:func:`qpax_batch_solver`); listed in :data:`rvdjax.peers.PEERS`.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from rvdjax.peers_host import PeerResult, _ms
from rvdjax.qp import QP, qp_objective

__all__ = ["solve_qpax", "qpax_batch_solver", "QpaxScaling", "ruiz_scaling"]


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
