"""The linear MPC optimal control problem (OCP) as a pytree of stage-wise arrays.

The problem solved at every MPC step (paper 000 Eq. 1-2, paper 003 Eq. 2.14), for stages
t = 0 .. N-1 with decision variables u_t (inputs) and x_{t+1} (predicted states)::

    minimise   sum_t (x_{t+1} - xr_t)^T Q_t (x_{t+1} - xr_t) + u_t^T R_t u_t
                     + q_t^T x_{t+1} + r_t^T u_t + rho_t^T max(0, Fx_t x_{t+1} - fx_t)
    subject to x_{t+1} = A_t x_t + B_t u_t + c_t,      x_0 = x0 (given)
               Fu_t u_t <= fu_t                        (hard: actuator limits)

The state rows Fx_t x_{t+1} <= fx_t are *soft*: each carries an exact L1 penalty rho (DESIGN
§3, "Feasibility"), so a state pushed outside a keep-out zone or cone by noise still yields a
usable plan. With rho larger than the constraint's multiplier the soft optimum equals the hard
one. As in the papers the cost has no factor 1/2 and omits the fixed x_0 term; the last stage's
Q is the terminal weight Q_f.

Every stage has a fixed number of rows (``mu`` input rows, ``mx`` state rows); rows that a
stage does not use are switched off by a 0/1 mask, so one array shape serves all stages.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = ["OCP", "make_ocp", "validate_ocp", "time_invariant_model"]


class OCP(NamedTuple):
    """Stage-wise data of one linear OCP. Shapes for horizon N, nx states, nu inputs.

    Attributes:
        A: (N, nx, nx) state transition of stage t (x_t -> x_{t+1}).
        B: (N, nx, nu) input matrix of stage t.
        c: (N, nx) affine dynamics term (zero for pure CW / double-integrator models).
        x0: (nx,) current state x_k.
        Q: (N, nx, nx) weight on x_{t+1}; Q[-1] is the terminal weight Q_f.
        R: (N, nu, nu) weight on u_t, positive definite.
        x_ref: (N, nx) reference (target) for x_{t+1}.
        q: (N, nx) linear cost on x_{t+1}.
        r: (N, nu) linear cost on u_t.
        Fu: (N, mu, nu) hard input rows, Fu_t u_t <= fu_t.
        fu: (N, mu)
        u_mask: (N, mu) 1.0 where an input row is active, 0.0 where it is padding.
        Fx: (N, mx, nx) soft state rows on x_{t+1}, Fx_t x_{t+1} <= fx_t.
        fx: (N, mx)
        rho: (N, mx) exact-penalty weight (cost per unit violation) of each state row.
        x_mask: (N, mx) 1.0 where a state row is active, 0.0 where it is padding.
    """

    A: jnp.ndarray
    B: jnp.ndarray
    c: jnp.ndarray
    x0: jnp.ndarray
    Q: jnp.ndarray
    R: jnp.ndarray
    x_ref: jnp.ndarray
    q: jnp.ndarray
    r: jnp.ndarray
    Fu: jnp.ndarray
    fu: jnp.ndarray
    u_mask: jnp.ndarray
    Fx: jnp.ndarray
    fx: jnp.ndarray
    rho: jnp.ndarray
    x_mask: jnp.ndarray

    @property
    def N(self) -> int:
        return self.B.shape[-3]

    @property
    def nx(self) -> int:
        return self.B.shape[-2]

    @property
    def nu(self) -> int:
        return self.B.shape[-1]

    @property
    def mu(self) -> int:
        return self.Fu.shape[-2]

    @property
    def mx(self) -> int:
        return self.Fx.shape[-2]


def _stage(a, N: int, shape: tuple[int, ...], name: str) -> np.ndarray:
    """Broadcast a time-invariant array (``shape``) or stage-wise array (N, *shape)."""
    a = np.asarray(a, dtype=float)
    if a.shape == shape:
        return np.broadcast_to(a, (N, *shape)).copy()
    if a.shape == (N, *shape):
        return a
    raise ValueError(
        f"{name} must have shape {shape} (time-invariant) or {(N, *shape)} (per stage), "
        f"got {a.shape}"
    )


def make_ocp(
    A,
    B,
    x0,
    Q,
    R,
    *,
    N: int,
    Q_f=None,
    c=None,
    x_ref=None,
    q=None,
    r=None,
    Fu=None,
    fu=None,
    u_mask=None,
    Fx=None,
    fx=None,
    rho=1e6,
    x_mask=None,
    u_max=None,
    check: bool = True,
) -> OCP:
    """Build an :class:`OCP` from time-invariant or stage-wise data, with input checks.

    Every argument may be given once (time-invariant) or per stage with a leading axis N.

    Args:
        A: (nx, nx) discrete state transition.
        B: (nx, nu) discrete input matrix.
        x0: (nx,) current state.
        Q: (nx, nx) stage state weight (positive semidefinite).
        R: (nu, nu) input weight (positive definite).
        N: horizon length (number of inputs), >= 1.
        Q_f: (nx, nx) terminal weight; defaults to Q.
        c: affine dynamics term, default 0.
        x_ref: state reference, default 0.
        q, r: linear cost terms, default 0.
        Fu, fu: hard input rows (Fu u <= fu); combined with ``u_max``.
        u_max: scalar or (nu,) symmetric input bound |u_i| <= u_max (paper 000 Eq. 5); adds
            2*nu box rows ahead of any ``Fu`` rows.
        Fx, fx: soft state rows (Fx x <= fx).
        rho: exact-penalty weight of the state rows (scalar or per row), > 0.
        u_mask, x_mask: 0/1 row masks; default all rows active.
        check: validate values (finite, R positive definite, Q semidefinite, ...). Leave on
            outside jit; a jitted caller builds its OCPs with :class:`OCP` directly.

    Returns:
        The OCP with float arrays (the default JAX float dtype).

    Raises:
        ValueError: naming the parameter and the allowed range.
    """
    if not isinstance(N, (int, np.integer)) or N < 1:
        raise ValueError(f"N (horizon) must be an integer >= 1, got {N!r}")
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    if B.ndim not in (2, 3):
        raise ValueError(f"B must have shape (nx, nu) or (N, nx, nu), got {B.shape}")
    nx, nu = B.shape[-2:]
    A = _stage(A, N, (nx, nx), "A")
    B = _stage(B, N, (nx, nu), "B")
    x0 = np.asarray(x0, dtype=float)
    if x0.shape != (nx,):
        raise ValueError(f"x0 must have shape ({nx},), got {x0.shape}")
    Qs = _stage(Q, N, (nx, nx), "Q")
    if Q_f is not None:
        Qs[-1] = np.asarray(Q_f, dtype=float)
    R = _stage(R, N, (nu, nu), "R")
    zeros_x = np.zeros((N, nx))
    c = zeros_x if c is None else _stage(c, N, (nx,), "c")
    x_ref = zeros_x if x_ref is None else _stage(x_ref, N, (nx,), "x_ref")
    q = zeros_x if q is None else _stage(q, N, (nx,), "q")
    r = np.zeros((N, nu)) if r is None else _stage(r, N, (nu,), "r")

    rows_F, rows_f = [], []
    if u_max is not None:
        umax = np.broadcast_to(np.asarray(u_max, dtype=float), (nu,))
        if check and not (np.all(np.isfinite(umax)) and np.all(umax > 0)):
            raise ValueError(f"u_max must be finite and > 0, got {u_max!r}")
        eye = np.eye(nu)
        rows_F.append(np.broadcast_to(np.concatenate([eye, -eye]), (N, 2 * nu, nu)))
        rows_f.append(np.broadcast_to(np.concatenate([umax, umax]), (N, 2 * nu)))
    if Fu is not None:
        Fu = np.asarray(Fu, dtype=float)
        mu = Fu.shape[-2]
        rows_F.append(_stage(Fu, N, (mu, nu), "Fu"))
        rows_f.append(_stage(fu, N, (mu,), "fu"))
    if rows_F:
        Fu = np.concatenate(rows_F, axis=1)
        fu = np.concatenate(rows_f, axis=1)
    else:  # no input rows: one inactive padding row keeps the shapes non-empty
        Fu, fu = np.zeros((N, 1, nu)), np.ones((N, 1))
        u_mask = np.zeros((N, 1))
    mu = Fu.shape[1]
    u_mask = np.ones((N, mu)) if u_mask is None else _stage(u_mask, N, (mu,), "u_mask")

    if Fx is None:
        Fx, fx = np.zeros((N, 1, nx)), np.ones((N, 1))
        x_mask = np.zeros((N, 1))
    else:
        Fx = np.asarray(Fx, dtype=float)
        mx = Fx.shape[-2]
        Fx = _stage(Fx, N, (mx, nx), "Fx")
        fx = _stage(fx, N, (mx,), "fx")
    mx = Fx.shape[1]
    x_mask = np.ones((N, mx)) if x_mask is None else _stage(x_mask, N, (mx,), "x_mask")
    rho = _stage(
        np.broadcast_to(np.asarray(rho, dtype=float), (mx,)) if np.ndim(rho) <= 1 else rho,
        N,
        (mx,),
        "rho",
    )

    ocp = OCP(A, B, c, x0, Qs, R, x_ref, q, r, Fu, fu, u_mask, Fx, fx, rho, x_mask)
    if check:
        validate_ocp(ocp)
    return OCP(*(jnp.asarray(a) for a in ocp))


def validate_ocp(ocp: OCP) -> None:
    """Check the values of a concrete (not traced) OCP; raise ValueError naming the field.

    Checks: every field finite; R_t symmetric positive definite; Q_t symmetric positive
    semidefinite; rho > 0 on active rows; masks in {0, 1}; the input rows have a strictly
    feasible point (u = 0 must satisfy fu > 0 on active rows, the cold start of the solver).
    """
    for name, a in zip(OCP._fields, ocp, strict=True):
        a = np.asarray(a)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf; every OCP entry must be finite")
    R = np.asarray(ocp.R)
    if not np.allclose(R, np.swapaxes(R, -1, -2), rtol=1e-10, atol=1e-12):
        raise ValueError("R must be symmetric")
    eig_R = np.linalg.eigvalsh(R)
    if np.min(eig_R) <= 0:
        raise ValueError(
            f"R must be positive definite (smallest eigenvalue > 0), got {np.min(eig_R):.3g}"
        )
    Q = np.asarray(ocp.Q)
    if not np.allclose(Q, np.swapaxes(Q, -1, -2), rtol=1e-10, atol=1e-12):
        raise ValueError("Q (and Q_f) must be symmetric")
    eig_Q = np.linalg.eigvalsh(Q)
    if np.min(eig_Q) < -1e-10 * max(1.0, np.max(np.abs(eig_Q))):
        raise ValueError(
            f"Q and Q_f must be positive semidefinite (eigenvalues >= 0), "
            f"got smallest eigenvalue {np.min(eig_Q):.3g}"
        )
    for name in ("u_mask", "x_mask"):
        m = np.asarray(getattr(ocp, name))
        if not np.all((m == 0) | (m == 1)):
            raise ValueError(f"{name} entries must be 0 or 1")
    active_x = np.asarray(ocp.x_mask) > 0
    if np.any(np.asarray(ocp.rho)[active_x] <= 0):
        raise ValueError("rho (state-constraint penalty) must be > 0 on active rows")
    active_u = np.asarray(ocp.u_mask) > 0
    if np.any(np.asarray(ocp.fu)[active_u] <= 0):
        raise ValueError(
            "fu must be > 0 on active input rows (u = 0 must be strictly feasible: actuator "
            "limits that exclude zero input are not supported)"
        )


def time_invariant_model(A, B, Q, R, Q_f, N: int):
    """Stage-wise (A, B, c, Q, R) of a time-invariant model over N stages, with the terminal
    weight Q_f on the last stage (jit-friendly; the arrays broadcast)."""
    nx, nu = B.shape
    return (
        jnp.broadcast_to(A, (N, nx, nx)),
        jnp.broadcast_to(B, (N, nx, nu)),
        jnp.zeros((N, nx), A.dtype),
        jnp.broadcast_to(Q, (N, nx, nx)).at[-1].set(Q_f),
        jnp.broadcast_to(R, (N, nu, nu)),
    )
