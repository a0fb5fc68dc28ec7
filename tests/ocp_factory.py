"""Random feasible OCPs for the solver tests.

Every problem of one shape class has the same array shapes (so a batch compiles once) and is
feasible for the *hard* QP by construction: a random input sequence strictly inside the input
rows is simulated, and each state row is placed a positive margin beyond that trajectory
(fx = Fx x_sim + margin). The state reference is pulled outside some state rows so that they
are active at the optimum.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from rvdjax.ocp import OCP, make_ocp

__all__ = ["ShapeClass", "SHAPE_CLASSES", "random_ocp", "random_ocp_batch"]


class ShapeClass(NamedTuple):
    """Array shapes of one class: nx states, nu inputs, horizon N, n_fu general input rows
    (after the 2 nu box rows) and mx soft state rows per stage."""

    nx: int
    nu: int
    N: int
    n_fu: int = 2
    mx: int = 3


SHAPE_CLASSES = {
    "small": ShapeClass(nx=2, nu=1, N=5, n_fu=1, mx=2),
    "medium": ShapeClass(nx=4, nu=2, N=20, n_fu=2, mx=3),
    "large": ShapeClass(nx=6, nu=3, N=30, n_fu=2, mx=3),
    "long": ShapeClass(nx=8, nu=4, N=60, n_fu=3, mx=4),
}


def _random_dynamics(rng, nx: int, nu: int):
    """A well-scaled (A, B): A a rotation-like matrix with spectral radius in [0.9, 1.03]."""
    M = rng.normal(size=(nx, nx))
    Qm, _ = np.linalg.qr(M)
    A = Qm * rng.uniform(0.9, 1.03) + 0.05 * rng.normal(size=(nx, nx)) / np.sqrt(nx)
    rad = np.max(np.abs(np.linalg.eigvals(A)))
    A *= min(1.0, 1.03 / rad)
    B = rng.normal(size=(nx, nu)) * rng.uniform(0.2, 1.0)
    return A, B


def _random_psd(rng, n: int, rank: int | None = None, lo: float = 0.1):
    rank = n if rank is None else rank
    V = rng.normal(size=(n, rank))
    return V @ np.diag(rng.uniform(lo, 2.0, size=rank)) @ V.T / n


def random_ocp(
    seed: int,
    shape: ShapeClass,
    *,
    time_varying: bool | None = None,
    rho: float | None = None,
    check: bool = True,
) -> OCP:
    """A random OCP of the given shape class that is feasible for the hard QP.

    Contents: 2 nu box rows |u_i| <= u_max and ``n_fu`` general halfspace rows Fu u <= fu with
    fu > 0 (u = 0 strictly feasible) per stage, ``mx`` soft halfspace rows on x_{t+1} per
    stage, some rows masked off, stage-varying (A_t, B_t, Q_t, R_t, x_ref_t, c_t) in roughly half
    the problems (``time_varying`` None), a singular Q in some, a reference pulled outside some
    state rows (so they are active), rho = 1e4 (well above the multipliers at this scaling).
    """
    rng = np.random.default_rng(seed)
    nx, nu, N, n_fu, mx = shape
    tv = bool(rng.integers(2)) if time_varying is None else time_varying

    A0, B0 = _random_dynamics(rng, nx, nu)
    if tv:
        A = A0 + 0.03 * rng.normal(size=(N, nx, nx)) / np.sqrt(nx)
        B = B0 * rng.uniform(0.7, 1.3, size=(N, 1, 1))
        c = 0.05 * rng.normal(size=(N, nx))
    else:
        A, B, c = A0, B0, np.zeros(nx)

    rank = nx if rng.uniform() < 0.7 else max(1, nx // 2)  # a singular Q now and then
    Q0 = _random_psd(rng, nx, rank)
    R0 = _random_psd(rng, nu, lo=0.5) + 0.05 * np.eye(nu)
    if tv:
        Q = Q0 * rng.uniform(0.5, 1.5, size=(N, 1, 1))
        R = R0 * rng.uniform(0.5, 1.5, size=(N, 1, 1))
    else:
        Q, R = Q0, R0
    Q_f = 5.0 * Q0 + _random_psd(rng, nx)

    u_max = rng.uniform(0.5, 2.0, size=nu)
    Fu = rng.normal(size=(N, n_fu, nu))
    fu = rng.uniform(0.3, 1.5, size=(N, n_fu))
    u_mask = np.ones((N, 2 * nu + n_fu))
    u_mask[:, 2 * nu :] = rng.uniform(size=(N, n_fu)) < 0.8  # mask some general rows

    # A strictly feasible input sequence and its trajectory.
    x0 = rng.normal(size=nx) * 2.0
    u_sim = rng.uniform(-0.7, 0.7, size=(N, nu)) * u_max
    for t in range(N):
        act = u_mask[t, 2 * nu :] > 0
        g = Fu[t] @ u_sim[t]
        ratio = np.where(act & (g > 0), fu[t] / np.where(g > 0, g, 1.0), np.inf)
        u_sim[t] *= min(1.0, 0.7 * ratio.min())
    A_s = np.broadcast_to(A, (N, nx, nx))
    B_s = np.broadcast_to(B, (N, nx, nu))
    c_s = np.broadcast_to(c, (N, nx))
    x_sim = np.empty((N, nx))
    x = x0
    for t in range(N):
        x = A_s[t] @ x + B_s[t] @ u_sim[t] + c_s[t]
        x_sim[t] = x

    # Soft state rows a positive margin beyond the simulated trajectory.
    Fx = rng.normal(size=(N, mx, nx))
    Fx /= np.linalg.norm(Fx, axis=-1, keepdims=True)
    fx = np.einsum("tij,tj->ti", Fx, x_sim) + rng.uniform(0.05, 1.0, size=(N, mx))
    x_mask = (rng.uniform(size=(N, mx)) < 0.85).astype(float)

    # Reference (always stage-varying): x_sim pulled outside a state row in ~60% of stages.
    x_ref = x_sim + 0.3 * rng.normal(size=(N, nx))
    pull = rng.uniform(size=N) < 0.6
    for t in np.flatnonzero(pull):
        j = int(rng.integers(mx))
        x_ref[t] += rng.uniform(1.0, 4.0) * Fx[t, j]

    return make_ocp(
        A,
        B,
        x0,
        Q,
        R,
        N=N,
        Q_f=Q_f,
        c=c,
        x_ref=x_ref,
        Fu=Fu,
        fu=fu,
        u_mask=u_mask,
        Fx=Fx,
        fx=fx,
        rho=1e4 if rho is None else rho,
        x_mask=x_mask,
        u_max=u_max,
        check=check,
    )


def random_ocp_batch(seeds, shape: ShapeClass, **kw) -> list[OCP]:
    """A list of :func:`random_ocp` problems, one per seed."""
    return [random_ocp(int(s), shape, **kw) for s in seeds]
