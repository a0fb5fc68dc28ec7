"""Navigation noise, thrust-amplitude error and minimum impulse bit for the closed loops.

DESIGN §4 and paper 003 Ch. 5 (the robustness study of the thesis):

* **Navigation noise** (paper 003 Eqs. 5.6-5.7): the guidance sees the relative state plus
  zero-mean Gaussian noise, sigma_rho on each position axis and sigma_rho_dot on each velocity
  axis (the thesis: 5 cm and 1 mm/s; it has no filter, and by default neither has rvdjax:
  ``LoopConfig(nav_filter=True)`` puts rvdjax's Kalman filter, :mod:`rvdjax.loop.navigation`,
  between the measurement and the guidance).
* **Thrust-amplitude error** (paper 003 Eqs. 5.2-5.3, Table 5.1, after Carpenter and Lee): the
  applied thrust is (1 + w(t)) times the commanded one, with w from the second-order
  Gauss-Markov model ``d[w, v]/dt = [[-1/tau, 1], [-omega_n^2, -2 xi omega_n]] [w, v] +
  [eta_w, eta_v]``. One independent process per input axis. Discretised exactly: transition
  Phi = expm(F dt) and process covariance Q_d = int_0^dt expm(F s) G G^T expm(F s)^T ds by Van
  Loan's matrix exponential — not by Euler.
* **Minimum impulse bit** (paper 003 Eqs. 2.4-2.6): a thruster cannot fire shorter than t_MIB;
  an axis whose commanded pulse m |dv| / F_max is shorter is not fired (the command is
  discarded, as in the thesis).

Assumptions (the thesis is silent; printed with every disturbed run):

* w is in **percent** (Fig. 5.1 shows errors of a few per cent; with eta_w = 3/sqrt(600) as a
  white-noise intensity on a fraction, w's steady-state standard deviation would be ~430 %):
  the applied factor is 1 + w / 100. Stationary 1-sigma of w: 4.6 % (derived:
  :func:`gm_stationary_std`).
* eta_w, eta_v are the standard deviations per sqrt(second) of the white noises (G = diag(eta)).
* w(0) ~ N(0, 1) % ("initialized with a random normal distribution with zero-mean and 1 sigma
  standard deviation"), v(0) = 0.
* The error is held over a sample (zero-order hold of w at the step start).

Everything is a pure function of arrays and a PRNG key (jit / vmap / grad).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Disturbances",
    "Draws",
    "disturbances",
    "THESIS_DISTURBANCES",
    "LAB_DISTURBANCES",
    "gm_discretize",
    "gm_init",
    "gm_step",
    "gm_stationary_std",
    "measure",
    "thrust_factor",
    "minimum_impulse_bit",
    "DISTURBANCE_NOTES",
]


class Draws(NamedTuple):
    """Given standard-normal draws that replace the PRNG's in a run (a verification's
    dispersion vector: a gradient can then shape a noise realisation). Each field is
    optional; ``None`` keeps the PRNG draw.

    Attributes:
        nav: (S, nx) navigation noise of MPC step k in row k (scaled by the sigmas).
        gm0: (n_axes,) w(0) of the Gauss-Markov thrust error (scaled by ``w0_sigma``).
        gm: (S, n_axes, 2) the Gauss-Markov driving noise of step k in row k.
        input_scale: (nu,) the truth's applied input is the command times this (a truth-only
            mass or inertia error: the guidance keeps its nominal model). Ideal forces only.
    """

    nav: jnp.ndarray | None = None
    gm0: jnp.ndarray | None = None
    gm: jnp.ndarray | None = None
    input_scale: jnp.ndarray | None = None


class Disturbances(NamedTuple):
    """Traced disturbance parameters (SI units; w in percent).

    Attributes:
        sigma_pos: () navigation noise, 1 sigma per position axis [m].
        sigma_vel: () navigation noise, 1 sigma per velocity axis [m/s].
        sigma_att: () navigation noise on attitude states (planar loops) [rad].
        tau: () Gauss-Markov time constant [s].
        omega_n: () natural frequency [rad/s].
        xi: () damping ratio.
        eta_w: () white-noise intensity on w [% / sqrt(s)].
        eta_v: () white-noise intensity on v [% / s / sqrt(s)].
        w0_sigma: () 1 sigma of w(0) [%].
        thrust_max: () force of one thruster along an axis (for the pulse width) [N].
        mib_s: () minimum pulse width t_MIB [s] (0: no minimum impulse bit).
    """

    sigma_pos: jnp.ndarray
    sigma_vel: jnp.ndarray
    sigma_att: jnp.ndarray
    tau: jnp.ndarray
    omega_n: jnp.ndarray
    xi: jnp.ndarray
    eta_w: jnp.ndarray
    eta_v: jnp.ndarray
    w0_sigma: jnp.ndarray
    thrust_max: jnp.ndarray
    mib_s: jnp.ndarray
    draws: Draws | None = None


def disturbances(
    *,
    sigma_pos: float = 0.05,
    sigma_vel: float = 1e-3,
    sigma_att: float = 0.0,
    tau: float = 3600.0,
    omega_n: float = 2.6e-4,
    xi: float = 1.0,
    eta_w: float = 3.0 / np.sqrt(600.0),
    eta_v: float = 1.1267e-8,
    w0_sigma: float = 1.0,
    thrust_max: float = 1.0,
    mib_s: float = 0.0,
) -> Disturbances:
    """Build and check :class:`Disturbances` (defaults: paper 003 Table 5.1 and Sec. 5.4).

    Raises ValueError naming the parameter: every value finite; sigmas, eta, w0_sigma and
    mib_s >= 0; tau, omega_n, xi and thrust_max > 0.
    """
    values = dict(
        sigma_pos=sigma_pos,
        sigma_vel=sigma_vel,
        sigma_att=sigma_att,
        tau=tau,
        omega_n=omega_n,
        xi=xi,
        eta_w=eta_w,
        eta_v=eta_v,
        w0_sigma=w0_sigma,
        thrust_max=thrust_max,
        mib_s=mib_s,
    )
    for name, v in values.items():
        if not np.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v}")
        strict = name in ("tau", "omega_n", "xi", "thrust_max")
        if (strict and not v > 0) or v < 0:
            raise ValueError(f"{name} must be {'> 0' if strict else '>= 0'}, got {v}")
    return Disturbances(**{k: jnp.asarray(float(v)) for k, v in values.items()})


# Paper 003 Table 5.1 and Sec. 5.4; thruster 0.5 N (the u_max reading of rvdjax.families.phases), no
# minimum impulse bit unless asked for.
THESIS_DISTURBANCES = dict(sigma_pos=0.05, sigma_vel=1e-3, thrust_max=0.5)

# Air-bearing test beds (papers 000-002 are silent): motion-capture navigation noise of a few
# millimetres, 1 mm/s and 0.5 deg; 0.15 N thrusters; the thesis' Gauss-Markov thrust error.
LAB_DISTURBANCES = dict(
    sigma_pos=0.005, sigma_vel=1e-3, sigma_att=float(np.deg2rad(0.5)), thrust_max=0.15
)

DISTURBANCE_NOTES = (
    "disturbed run (paper 003 Ch. 5): navigation noise sigma = {sigma_pos:g} m, "
    "{sigma_vel:g} m/s per axis; thrust-amplitude error (1 + w / 100) with the "
    "Carpenter-Lee Gauss-Markov model of Table 5.1 per input axis (w in percent, assumed; "
    "eta as white-noise intensities; w(0) ~ N(0, 1) %; held over each step); "
    "minimum impulse bit {mib_s:g} s",
)


def _gm_matrices(d: Disturbances):
    F = jnp.array([[-1.0 / d.tau, 1.0], [-(d.omega_n**2), -2.0 * d.xi * d.omega_n]])
    G = jnp.diag(jnp.stack([d.eta_w, d.eta_v]))
    return F, G


def gm_discretize(d: Disturbances, dt):
    """Exact discretisation of the Gauss-Markov model over ``dt`` [s] (Van Loan, 1978).

    Returns:
        (Phi (2, 2), Q_d (2, 2)): w_{k+1} = Phi w_k + e_k, e_k ~ N(0, Q_d).
    """
    F, G = _gm_matrices(d)
    M = jnp.block([[-F, G @ G.T], [jnp.zeros((2, 2)), F.T]]) * dt
    E = jax.scipy.linalg.expm(M)
    Phi = E[2:, 2:].T
    Qd = Phi @ E[:2, 2:]
    return Phi, 0.5 * (Qd + Qd.T)


def _given(d: Disturbances, name: str):
    return None if d.draws is None else getattr(d.draws, name)


def gm_init(key, d: Disturbances, n_axes: int):
    """(n_axes, 2) initial Gauss-Markov states: w(0) ~ N(0, w0_sigma^2) %, v(0) = 0 (the
    standard-normal draw from ``key``, or ``d.draws.gm0`` when given)."""
    z = _given(d, "gm0")
    z = jax.random.normal(key, (n_axes,)) if z is None else z
    w = d.w0_sigma * z
    return jnp.stack([w, jnp.zeros_like(w)], axis=-1)


def gm_step(key, state, d: Disturbances, dt, k=None):
    """Advance (n_axes, 2) Gauss-Markov states by ``dt`` with the exact discretisation (the
    driving noise from ``key``, or row ``k`` of ``d.draws.gm`` when given)."""
    Phi, Qd = gm_discretize(d, dt)
    # Q_d can be numerically semidefinite (eta_v is tiny): a jittered Cholesky is exact enough
    L = jnp.linalg.cholesky(Qd + 1e-30 * jnp.eye(2))
    z = _given(d, "gm")
    z = jax.random.normal(key, state.shape) if z is None else z[k]
    e = z @ L.T
    return state @ Phi.T + e


def gm_stationary_std(d: Disturbances, dt=None):
    """Stationary 1-sigma of w [%] of the Gauss-Markov model.

    The exact discretisation over any ``dt`` has the stationary covariance of the continuous
    model, so ``dt`` is not needed: P solves the continuous Lyapunov equation
    F P + P F^T + G G^T = 0, here (I (x) F + F (x) I) vec(P) = -vec(G G^T) (no matrix
    exponential: the filter evaluates it every step). Paper 003 Table 5.1: 4.62 %.
    """
    del dt
    F, G = _gm_matrices(d)
    eye = jnp.eye(2, dtype=F.dtype)
    K = jnp.kron(eye, F) + jnp.kron(F, eye)
    P = jnp.linalg.solve(K, -(G @ G.T).reshape(-1)).reshape(2, 2)
    return jnp.sqrt(P[0, 0])


def thrust_factor(state):
    """(n_axes,) multiplicative thrust factor 1 + w / 100 (w in percent)."""
    return 1.0 + state[..., 0] / 100.0


def measure(key, x, d: Disturbances, pos, vel, att=(), k=None):
    """The state the guidance sees: x plus Gaussian noise on the position, velocity and
    attitude components (index tuples ``pos``, ``vel``, ``att``; other entries exact); the
    standard-normal draw from ``key``, or row ``k`` of ``d.draws.nav`` when given."""
    sigma = jnp.zeros(x.shape[-1], x.dtype)
    sigma = sigma.at[jnp.asarray(pos, int)].set(d.sigma_pos)
    sigma = sigma.at[jnp.asarray(vel, int)].set(d.sigma_vel)
    if len(att):
        sigma = sigma.at[jnp.asarray(att, int)].set(d.sigma_att)
    z = _given(d, "nav")
    z = jax.random.normal(key, x.shape, x.dtype) if z is None else z[k]
    return x + sigma * z


def minimum_impulse_bit(impulse, d: Disturbances):
    """Zero every axis whose pulse |J| / F_max is shorter than t_MIB (paper 003 Eq. 2.6).

    Args:
        impulse: (..., n_axes) commanded impulse per axis [N s] (m dv for impulsive inputs,
            F Ts for a zero-order hold).
    """
    pulse = jnp.abs(impulse) / d.thrust_max
    return jnp.where(pulse < d.mib_s, 0.0, impulse)
