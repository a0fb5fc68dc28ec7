"""Named OCP instances from the papers: the ``fastmpc-3d`` first MPC step (paper 000 Table 1).

Obstacle keep-out rows by direct linearisation, paper 000 Eqs. 6-8; model and weights, paper 000
§IV.A and Table 1; terminal weight Q_f = DARE solution (DESIGN §5).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.dynamics import cw_continuous, dare, discretize_zoh, mean_motion
from rvdjax.ocp import OCP, make_ocp

__all__ = [
    "FASTMPC3D",
    "obstacle_rows",
    "obstacle_centres",
    "drift_positions",
    "fastmpc3d_model",
    "fastmpc3d_first_step",
    "fastmpc3d_first_step_batch",
    "perturbed_x0",
    "stack_ocps",
]

# Paper 000 §IV.A and Table 1 (three-dimensional simulations).
FASTMPC3D = {
    "altitude_m": 705e3,  # target orbit altitude [m]
    "mass": 6500.0,  # chaser mass [kg]
    "N": 30,  # horizon
    "ts": 15.0,  # discretisation time Td [s], zero-order hold
    "Q": (1.0, 1.0, 1.0, 100.0, 100.0, 100.0),  # diagonal
    "R": (100.0, 100.0, 100.0),  # diagonal
    "u_max": 20.0,  # [N], per axis
    "x0": (50.0, -1000.0, 10.0, 0.0, 0.0, 0.0),  # chaser (x, y, z, vx, vy, vz) [m, m/s]
    "obstacles": (
        (-30.0, -800.0, 10.0, -0.075, -0.005, 0.015),  # obstacle 1 initial state
        (-100.0, 0.0, -40.0, 0.07, -0.16, 0.01),  # obstacle 2 initial state
    ),
    "radii": (20.0, 50.0),  # spherical keep-out radii [m]
    "hold_radius": 2.3,  # mission ends at this distance from the target [m]
}

# Exact L1 penalty of the keep-out rows. The multiplier of the active keep-out row in the hard
# first-step QP is ~1e6 (cost per unit of the dimensionless row (r0-o)^T S (r-o)) for the
# Table 1 state and its perturbations; 1e8 leaves a margin of ~100x.
DEFAULT_RHO = 1e8


def obstacle_rows(p_guess, centres, radii, nx: int | None = None):
    """Linearised spherical keep-out rows (paper 000 Eqs. 6-8, direct linearisation).

    For stage t and obstacle j with centre o, radius r and shape matrix S = I / r^2, the
    expansion point is the point of the sphere on the segment from o to the guessed chaser
    position p: r0 = o + (p - o) / sqrt((p - o)^T S (p - o)). Since (r0 - o)^T S (r0 - o) = 1,
    Eq. 8 reduces to (r0 - o)^T S (r - o) >= 1, returned as the row

        -(r0 - o)^T S r <= -1 - (r0 - o)^T S o

    acting on the position part (the first ``dim`` entries) of the state. The row is a
    supporting half-space of the sphere, so it is conservative (it excludes the whole ball).
    Pure JAX: jittable, vmappable and differentiable.

    Args:
        p_guess: (N, dim) guessed chaser positions [m] at the constrained stages.
        centres: (N, n_obs, dim) obstacle centres [m] at the same instants.
        radii: (n_obs,) keep-out radii [m], > 0.
        nx: state dimension (positions first); default 2 * dim.

    Returns:
        (Fx (N, n_obs, nx), fx (N, n_obs)): rows Fx x <= fx on the state.
        If a guess coincides with an obstacle centre the expansion direction is the first
        axis (radial for CW).
    """
    p_guess = jnp.asarray(p_guess, dtype=float)
    centres = jnp.asarray(centres, dtype=float)
    radii = jnp.asarray(radii, dtype=float)
    dim = p_guess.shape[-1]
    nx = 2 * dim if nx is None else nx
    d = p_guess[:, None, :] - centres  # (N, n_obs, dim)
    dist = jnp.linalg.norm(d, axis=-1, keepdims=True)
    e1 = jnp.zeros(dim).at[0].set(1.0)
    safe = dist > 1e-12
    unit = jnp.where(safe, d / jnp.where(safe, dist, 1.0), e1)  # (p - o) / |p - o|
    # r0 - o = r * unit, so a = S (r0 - o) = unit / r.
    a = unit / radii[:, None]
    Fx = jnp.zeros((*a.shape[:2], nx)).at[..., :dim].set(-a)
    fx = -1.0 - jnp.sum(a * centres, axis=-1)
    return Fx, fx


def obstacle_centres(obstacles, N: int, ts, t0=0.0):
    """Obstacle centres at the stage instants t0 + (t+1) ts, t = 0..N-1.

    Assumption: obstacles move on straight lines with constant velocity in the LVLH frame,
    o(t) = o_0 + v_0 t (paper 000 says only "constant translational velocity"; the obstacles'
    own relative orbital dynamics are ignored).

    Args:
        obstacles: (n_obs, 2 * dim) obstacle states (position, velocity) at time 0 [m, m/s].
        N: number of stages.
        ts: sampling time [s].
        t0: current time [s].

    Returns:
        (N, n_obs, dim) centres [m].
    """
    obstacles = jnp.asarray(obstacles, dtype=float)
    dim = obstacles.shape[-1] // 2
    times = t0 + ts * jnp.arange(1, N + 1, dtype=float)
    return obstacles[None, :, :dim] + times[:, None, None] * obstacles[None, :, dim:]


def drift_positions(Ad, x0, N: int, dim: int = 3):
    """Unforced (u = 0) predicted positions x_{t+1}[:dim] = (Ad^{t+1} x0)[:dim], shape (N, dim)."""

    def step(x, _):
        x = Ad @ x
        return x, x[:dim]

    _, p = jax.lax.scan(step, jnp.asarray(x0, dtype=float), None, length=N)
    return p


def fastmpc3d_model(ts: float | None = None):
    """Discrete CW model of ``fastmpc-3d``: (Ad (6, 6), Bd (6, 3), P_dare (6, 6)).

    ZOH at Ts = 15 s (or ``ts``), n at 705 km, m = 6500 kg; P_dare is the DARE solution for
    Q = diag(1,1,1,100,100,100), R = diag(100,100,100) (the terminal weight Q_f).
    """
    p = FASTMPC3D
    ts = p["ts"] if ts is None else ts
    Ac, Bc = cw_continuous(mean_motion(altitude_m=p["altitude_m"]), p["mass"])
    Ad, Bd = discretize_zoh(Ac, Bc, ts)
    P = dare(Ad, Bd, np.diag(p["Q"]), np.diag(p["R"]))
    return Ad, Bd, P


def _keepout_rows(x0, Ad, centres, radii):
    """Keep-out rows of the first MPC step: expansion about the unforced drift path of x0."""
    p_guess = drift_positions(Ad, x0, centres.shape[0], centres.shape[-1])
    return obstacle_rows(p_guess, centres, radii, nx=x0.shape[-1])


def fastmpc3d_first_step(
    x0=None, obstacles: bool = True, N: int = 30, rho: float = DEFAULT_RHO
) -> OCP:
    """The first-step OCP of the ``fastmpc-3d`` scenario (paper 000 §IV.A, Table 1).

    CW at 705 km altitude, m = 6500 kg, ZOH at Ts = 15 s, Q = diag(1,1,1,100,100,100),
    R = diag(100,100,100), Q_f = DARE solution, |u_i| <= 20 N (6 hard box rows per stage),
    target / holding point at the origin (x_ref = 0). With ``obstacles``, two spherical keep-out
    zones (radii 20 m and 50 m; initial states from Table 1, moving on straight lines with
    constant velocity, see :func:`obstacle_centres`) give 2 soft rows per stage on x_{t+1} at
    time (t+1) Ts, linearised (paper 000 Eqs. 6-8) about the chaser's unforced drift path from
    x0. (A straight line to the target as the guess runs through obstacle 1 and makes the hard
    QP infeasible.)

    Args:
        x0: (6,) chaser state [m, m/s]; default Table 1, (50, -1000, 10, 0, 0, 0).
        obstacles: include the keep-out rows (mx = 2) or not (no state rows).
        N: horizon, default 30.
        rho: exact L1 penalty of the keep-out rows (large enough that the soft optimum equals
            the hard one for the Table 1 state).

    Returns:
        The :class:`~rvdjax.ocp.OCP`: 270 plan variables, 180 equalities and 240 hard
        inequalities (180 without obstacles) in the QP of :func:`rvdjax.qp.to_qp`.
    """
    p = FASTMPC3D
    x0 = np.asarray(p["x0"] if x0 is None else x0, dtype=float)
    Ad, Bd, P = fastmpc3d_model()
    kw = {}
    if obstacles:
        centres = obstacle_centres(np.asarray(p["obstacles"]), N, p["ts"])
        Fx, fx = _keepout_rows(jnp.asarray(x0), Ad, centres, jnp.asarray(p["radii"]))
        kw = {"Fx": np.asarray(Fx), "fx": np.asarray(fx), "rho": rho}
    return make_ocp(
        np.asarray(Ad),
        np.asarray(Bd),
        x0,
        np.diag(p["Q"]),
        np.diag(p["R"]),
        N=N,
        Q_f=np.asarray(P),
        u_max=p["u_max"],
        **kw,
    )


def perturbed_x0(key_or_seed, batch: int, scale_pos: float = 20.0, scale_vel: float = 0.05):
    """A batch of chaser states uniformly perturbed around the Table 1 chaser state.

    Args:
        key_or_seed: a JAX PRNG key or an integer seed.
        batch: number of states.
        scale_pos: half-width of the uniform position perturbation per axis [m].
        scale_vel: half-width of the uniform velocity perturbation per axis [m/s].

    Returns:
        (batch, 6) states [m, m/s].
    """
    key = jax.random.PRNGKey(key_or_seed) if isinstance(key_or_seed, int) else key_or_seed
    scale = jnp.array([scale_pos] * 3 + [scale_vel] * 3)
    delta = jax.random.uniform(key, (batch, 6), minval=-1.0, maxval=1.0) * scale
    return jnp.asarray(FASTMPC3D["x0"]) + delta


def stack_ocps(ocps) -> OCP:
    """Stack a sequence of same-shape OCPs into one batched OCP (leading batch axis)."""
    return jax.tree.map(lambda *a: jnp.stack(a), *ocps)


def fastmpc3d_first_step_batch(
    x0s, obstacles: bool = True, N: int = 30, rho: float = DEFAULT_RHO
) -> OCP:
    """Batched :func:`fastmpc3d_first_step` for states x0s (batch, 6): every field gains a
    leading batch axis. The shared data are built (and checked) once; x0 and the keep-out rows
    (which depend on x0 through the drift guess) are computed with ``jax.vmap``.
    """
    x0s = jnp.asarray(x0s, dtype=float)
    if x0s.ndim != 2 or x0s.shape[1] != 6:
        raise ValueError(f"x0s must have shape (batch, 6), got {x0s.shape}")
    if not bool(jnp.all(jnp.isfinite(x0s))):
        raise ValueError("x0s must be finite")
    base = fastmpc3d_first_step(obstacles=obstacles, N=N, rho=rho)
    B = x0s.shape[0]
    batched = jax.tree.map(lambda a: jnp.broadcast_to(a, (B, *a.shape)), base)
    batched = batched._replace(x0=x0s)
    if obstacles:
        p = FASTMPC3D
        centres = obstacle_centres(jnp.asarray(p["obstacles"]), N, p["ts"])
        radii = jnp.asarray(p["radii"])
        Fx, fx = jax.vmap(lambda x: _keepout_rows(x, base.A[0], centres, radii))(x0s)
        batched = batched._replace(Fx=Fx, fx=fx)
    return batched
