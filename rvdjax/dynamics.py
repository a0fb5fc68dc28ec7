"""Relative-motion models, their exact discretisation and the discrete Riccati equation in JAX.

Sources: Clohessy–Wiltshire (CW/Hill) equations and mean motion, paper 000 Eq. 3; planar
three-DOF test-bed model, paper 000 Eq. 4; zero-order-hold discretisation, paper 000 §II.B;
impulsive discretisation B̄ = Ā·[0; I], paper 003 Eq. 3.1. Everything here is pure JAX and
differentiable (``jax.grad`` / ``jax.jacfwd``) with respect to the sampling time, the mean motion,
the mass and the inertia. Argument checks run only on concrete values (Python / NumPy / concrete
JAX arrays) and are skipped for JAX tracers, so every function stays jittable.
"""

from __future__ import annotations

import functools
import operator

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import expm

__all__ = [
    "zoh_states",
    "MU_EARTH",
    "R_EARTH",
    "mean_motion",
    "cw_continuous",
    "planar3dof_continuous",
    "planar2dof_continuous",
    "discretize_zoh",
    "discretize_impulsive",
    "dare",
    "check_positive",
    "check_finite",
]

MU_EARTH = 3.986004418e14  # Earth's gravitational parameter [m^3/s^2]
R_EARTH = 6378137.0  # Earth's equatorial radius (WGS-84) [m]


# --------------------------------------------------------------------------------------------
# Input validation (concrete values only)
# --------------------------------------------------------------------------------------------


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def check_finite(name: str, value) -> None:
    """Raise ValueError naming ``name`` if a concrete ``value`` has a NaN or inf entry.

    Tracers (inside jit / grad / vmap) are not checked.
    """
    if _is_tracer(value):
        return
    a = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite (no NaN or inf), got {value!r}")


def check_positive(name: str, value, unit: str = "") -> None:
    """Raise ValueError naming ``name`` unless a concrete ``value`` is finite and > 0.

    Tracers (inside jit / grad / vmap) are not checked.
    """
    if _is_tracer(value):
        return
    a = np.asarray(value, dtype=float)
    suffix = f" [{unit}]" if unit else ""
    if not np.all(np.isfinite(a)) or not np.all(a > 0):
        raise ValueError(
            f"{name}{suffix} must be finite and > 0 (allowed range (0, inf)), got {value!r}"
        )


def _check_square(name: str, M) -> None:
    if M.ndim != 2 or M.shape[0] != M.shape[1]:
        raise ValueError(f"{name} must be a square matrix (nx, nx), got shape {M.shape}")


# --------------------------------------------------------------------------------------------
# Continuous-time models
# --------------------------------------------------------------------------------------------


def mean_motion(altitude_m=None, semi_major_axis_m=None):
    """Mean motion n = sqrt(mu / a^3) [rad/s] of a circular orbit (paper 000, after Eq. 3).

    Give exactly one of:
        altitude_m: altitude above R_EARTH [m], > 0 (a = R_EARTH + altitude).
        semi_major_axis_m: semi-major axis a [m], > 0.

    Returns:
        n [rad/s], scalar (JAX array).

    Raises:
        ValueError: if both or neither argument is given, or the value is not finite and > 0.
    """
    if (altitude_m is None) == (semi_major_axis_m is None):
        raise ValueError(
            "mean_motion needs exactly one of altitude_m or semi_major_axis_m "
            f"(got altitude_m={altitude_m!r}, semi_major_axis_m={semi_major_axis_m!r})"
        )
    if altitude_m is not None:
        check_positive("altitude_m", altitude_m, "m")
        return _mean_motion(R_EARTH + jnp.asarray(altitude_m, dtype=float))
    check_positive("semi_major_axis_m", semi_major_axis_m, "m")
    return _mean_motion(jnp.asarray(semi_major_axis_m, dtype=float))


# The models' and discretisations' arithmetic is jitted (checks stay outside, on the values
# as given): building a scenario's parameters ran it op by op, and each eager op's first call
# compiles a program of its own, about 1 s of a 6 s `rvdjax run` (2026-11-28). The jitted
# results are the same bits (every registered scenario's parameters compared).
@jax.jit
def _mean_motion(a):
    return jnp.sqrt(MU_EARTH / a**3)


def cw_continuous(n, mass):
    """Clohessy–Wiltshire (Hill) equations, paper 000 Eq. 3, in state-space form.

    Frame: LVLH centred on the target, x radial (outward), y along-track, z cross-track.
    State (x, y, z, vx, vy, vz) [m, m/s]; input force (ux, uy, uz) [N]::

        xdd =  3 n^2 x + 2 n yd + ux / m
        ydd = -2 n xd           + uy / m
        zdd = -n^2 z            + uz / m

    Args:
        n: mean motion of the target orbit [rad/s], > 0.
        mass: chaser mass [kg], > 0.

    Returns:
        (Ac (6, 6), Bc (6, 3)) with Bc = [0; I / mass].
    """
    check_positive("n (mean motion)", n, "rad/s")
    check_positive("mass", mass, "kg")
    return _cw_continuous(jnp.asarray(n, dtype=float), jnp.asarray(mass, dtype=float))


@jax.jit
def _cw_continuous(n, mass):
    z = jnp.zeros(())
    Ac = jnp.array(
        [
            [z, z, z, 1.0, z, z],
            [z, z, z, z, 1.0, z],
            [z, z, z, z, z, 1.0],
            [3.0 * n**2, z, z, z, 2.0 * n, z],
            [z, z, z, -2.0 * n, z, z],
            [z, z, -(n**2), z, z, z],
        ]
    )
    Bc = jnp.concatenate([jnp.zeros((3, 3)), jnp.eye(3) / mass])
    return Ac, Bc


def planar3dof_continuous(mass, inertia):
    """Planar rigid body with three DOF, paper 000 Eq. 4 (inertial frame, no orbital terms).

    State (x, y, theta, vx, vy, omega) [m, m, rad, m/s, m/s, rad/s]; input (Fx, Fy, torque)
    [N, N, N·m]: xdd = Fx / m, ydd = Fy / m, thetadd = torque / Iz.

    Args:
        mass: mass [kg], > 0.
        inertia: moment of inertia about z, Iz [kg·m^2], > 0.

    Returns:
        (Ac (6, 6), Bc (6, 3)).
    """
    check_positive("mass", mass, "kg")
    check_positive("inertia", inertia, "kg m^2")
    return _planar3dof(jnp.asarray(mass, dtype=float), jnp.asarray(inertia, dtype=float))


@jax.jit
def _planar3dof(mass, inertia):
    Ac = jnp.block([[jnp.zeros((3, 3)), jnp.eye(3)], [jnp.zeros((3, 3)), jnp.zeros((3, 3))]])
    inv = jnp.stack([1.0 / mass, 1.0 / mass, 1.0 / inertia])
    Bc = jnp.concatenate([jnp.zeros((3, 3)), jnp.diag(inv)])
    return Ac, Bc


def planar2dof_continuous(mass):
    """Planar double integrator (translation only), paper 001 model.

    State (x, y, vx, vy) [m, m/s]; input (Fx, Fy) [N].

    Args:
        mass: mass [kg], > 0.

    Returns:
        (Ac (4, 4), Bc (4, 2)) with Bc = [0; I / mass].
    """
    check_positive("mass", mass, "kg")
    return _planar2dof(jnp.asarray(mass, dtype=float))


@jax.jit
def _planar2dof(mass):
    Ac = jnp.block([[jnp.zeros((2, 2)), jnp.eye(2)], [jnp.zeros((2, 2)), jnp.zeros((2, 2))]])
    Bc = jnp.concatenate([jnp.zeros((2, 2)), jnp.eye(2) / mass])
    return Ac, Bc


# --------------------------------------------------------------------------------------------
# Discretisation
# --------------------------------------------------------------------------------------------


def discretize_zoh(Ac, Bc, ts):
    """Exact zero-order-hold discretisation (paper 000 §II.B).

    [[Ad, Bd], [0, I]] = expm([[Ac, Bc], [0, 0]] * ts), so that
    x_{k+1} = Ad x_k + Bd u_k for an input held constant over [k ts, (k+1) ts).

    Args:
        Ac: (nx, nx) continuous state matrix [1/s].
        Bc: (nx, nu) continuous input matrix (units of state rate per input unit).
        ts: sampling time [s], > 0.

    Returns:
        (Ad (nx, nx), Bd (nx, nu)).
    """
    check_positive("ts (sampling time)", ts, "s")
    Ac = jnp.asarray(Ac, dtype=float)
    Bc = jnp.asarray(Bc, dtype=float)
    _check_square("Ac", Ac)
    if Bc.ndim != 2 or Bc.shape[0] != Ac.shape[0]:
        raise ValueError(f"Bc must have shape ({Ac.shape[0]}, nu), got {Bc.shape}")
    check_finite("Ac", Ac)
    check_finite("Bc", Bc)
    return _zoh(Ac, Bc, ts)


@jax.jit
def _zoh(Ac, Bc, ts):
    nx, nu = Bc.shape
    M = jnp.zeros((nx + nu, nx + nu))
    M = M.at[:nx, :nx].set(Ac).at[:nx, nx:].set(Bc)
    E = expm(M * ts)
    return E[:nx, :nx], E[:nx, nx:]


def discretize_impulsive(Ac, ts, nv: int | None = None):
    """Impulsive discretisation, paper 003 Eq. 3.1: Ad = expm(Ac ts), Bd = Ad @ [0; I].

    The input is a velocity change Δv [m/s] applied at the *start* of the interval, after which
    the state drifts freely for ts: x_{k+1} = Ad (x_k + [0; Δv_k]).

    Args:
        Ac: (nx, nx) continuous state matrix; the last ``nv`` states are the velocities.
        ts: sampling time [s], > 0.
        nv: number of velocity states (= number of inputs); default nx // 2.

    Returns:
        (Ad (nx, nx), Bd (nx, nv)).
    """
    check_positive("ts (sampling time)", ts, "s")
    Ac = jnp.asarray(Ac, dtype=float)
    _check_square("Ac", Ac)
    check_finite("Ac", Ac)
    nx = Ac.shape[0]
    if nv is None:
        if nx % 2:
            raise ValueError(f"nv must be given when nx is odd (nx = {nx})")
        nv = nx // 2
    if not (isinstance(nv, (int, np.integer)) and 1 <= nv <= nx):
        raise ValueError(f"nv (number of velocity states) must be an integer in [1, {nx}]")
    return _impulsive(Ac, ts, int(nv))


@functools.partial(jax.jit, static_argnames="nv")
def _impulsive(Ac, ts, nv: int):
    nx = Ac.shape[0]
    Ad = expm(Ac * ts)
    Bbar = jnp.concatenate([jnp.zeros((nx - nv, nv)), jnp.eye(nv)])
    return Ad, Ad @ Bbar


# --------------------------------------------------------------------------------------------
# Discrete algebraic Riccati equation
# --------------------------------------------------------------------------------------------


def dare(A, B, Q, R, iters: int = 64):
    """Stabilising solution P of the discrete algebraic Riccati equation

        P = A^T P A - A^T P B (R + B^T P B)^{-1} B^T P A + Q

    by the structure-preserving doubling algorithm (SDA; Chu, Fan, Lin & Wang 2004) with a
    fixed number of iterations, unrolled with ``lax.fori_loop`` so that it is jittable and
    forward- and reverse-differentiable. SDA converges quadratically: the error after k
    iterations is ~rho(A_cl)^(2^(k+1)), so the default 64 iterations is ample even for a
    closed-loop spectral radius within 1e-12 of 1 (the marginally stable CW case converges in
    ~15). Extra iterations are harmless: once converged, A_k underflows to 0 and P is a fixed
    point.

    Requirements: (A, B) stabilisable, (A, Q^{1/2}) detectable, R positive definite.

    Args:
        A: (nx, nx) discrete state matrix.
        B: (nx, nu) discrete input matrix.
        Q: (nx, nx) symmetric positive semidefinite state weight.
        R: (nu, nu) symmetric positive definite input weight.
        iters: number of doubling iterations (static).

    Returns:
        P: (nx, nx) symmetric positive semidefinite solution.
    """
    A = jnp.asarray(A, dtype=float)
    B = jnp.asarray(B, dtype=float)
    Q = jnp.asarray(Q, dtype=float)
    R = jnp.asarray(R, dtype=float)
    _check_square("A", A)
    nx = A.shape[0]
    if B.ndim != 2 or B.shape[0] != nx:
        raise ValueError(f"B must have shape ({nx}, nu), got {B.shape}")
    nu = B.shape[1]
    if Q.shape != (nx, nx):
        raise ValueError(f"Q must have shape ({nx}, {nx}), got {Q.shape}")
    if R.shape != (nu, nu):
        raise ValueError(f"R must have shape ({nu}, {nu}), got {R.shape}")
    for name, M in (("A", A), ("B", B), ("Q", Q), ("R", R)):
        check_finite(name, M)
    if not _is_tracer(R) and np.min(np.linalg.eigvalsh(np.asarray(R))) <= 0:
        raise ValueError("R must be symmetric positive definite")

    return _dare_sda(A, B, Q, R, iters)


@functools.partial(jax.jit, static_argnames="iters")
def _dare_sda(A, B, Q, R, iters: int):
    """The doubling iterations of :func:`dare` (jitted: building a scenario's parameters
    calls it per phase, and op-by-op dispatch of the loop costs ~0.2 s a call)."""
    nx = A.shape[0]
    eye = jnp.eye(nx)
    G0 = B @ jnp.linalg.solve(R, B.T)
    G0 = 0.5 * (G0 + G0.T)
    H0 = 0.5 * (Q + Q.T)

    def body(_, carry):
        Ak, Gk, Hk = carry
        W = eye + Gk @ Hk
        # V1 = W^{-1} A_k, V2 = W^{-1} G_k
        V = jnp.linalg.solve(W, jnp.concatenate([Ak, Gk], axis=1))
        V1, V2 = V[:, :nx], V[:, nx:]
        G_new = Gk + Ak @ V2 @ Ak.T
        H_new = Hk + Ak.T @ Hk @ V1
        A_new = Ak @ V1
        return A_new, 0.5 * (G_new + G_new.T), 0.5 * (H_new + H_new.T)

    _, _, P = jax.lax.fori_loop(0, iters, body, (A, G0, H0))
    return P


ZOH_TERMS = 12


def zoh_states(Ac, Bc, x, u, taus, mv=operator.matmul):
    """States at times ``taus`` (M,) [s] after ``x`` under the constant input ``u``:
    x(tau) = e^{Ac tau} x + int_0^tau e^{Ac s} ds Bc u, by the power series of the
    augmented matrix [[Ac, Bc], [0, 0]] to :data:`ZOH_TERMS` terms (Horner's rule). Exact to
    float64 rounding while ||Ac|| tau <= 0.1 (CW with n tau <= 0.1: a 60 s step in LEO).
    ``mv(A, x)``: the matrix-vector product (a GPU program passes a multiply and sum, which
    XLA fuses, where ``A @ x`` of a matrix shared by a batch is a launch of its own per term).

    Returns:
        (M, nx) states.
    """
    Ac = jnp.asarray(Ac)
    f = mv(Ac, x) + mv(Bc, u)  # d/dt of the state at tau = 0

    def one(tau):
        # x(tau) = x + sum_{k>=1} tau^k / k! Ac^{k-1} f  (the input is constant)
        acc = f
        for k in range(ZOH_TERMS, 1, -1):
            acc = f + (tau / k) * mv(Ac, acc)
        return x + tau * acc

    return jax.vmap(one)(jnp.asarray(taus))
