"""Named OCP instances: the ``fastmpc-3d`` first MPC step (paper 000 Table 1), the problem of
the solver benchmark, the demo and the solver tests.

It is the first step of the scenario's closed loop, built by the rendezvous family itself
(:mod:`rvdjax.families.rendezvous`): keep-out rows by direct linearisation about the chaser's
unforced drift (paper 000 Eqs. 6-8), model and weights of §IV.A and Table 1, terminal weight
Q_f = DARE solution.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from rvdjax.families import rendezvous as rv
from rvdjax.ocp import OCP, validate_ocp
from rvdjax.scenarios.paper000 import FASTMPC3D as _PHYSICAL
from rvdjax.scenarios.paper000 import FASTMPC3D_X0

__all__ = [
    "FASTMPC3D",
    "DEFAULT_RHO",
    "fastmpc3d_params",
    "fastmpc3d_first_step",
    "fastmpc3d_step",
    "fastmpc3d_first_step_batch",
    "perturbed_x0",
    "stack_ocps",
]

#: Paper 000 Sec. IV.A and Table 1 (the scenario's physical values and initial state).
FASTMPC3D = {**_PHYSICAL, "x0": FASTMPC3D_X0, "N": 30}

#: Exact L1 penalty of the keep-out rows [per metre, per obstacle]: 1e8 per unit of relative
#: penetration; the multiplier of the active keep-out row of the first-step QP is ~100x
#: smaller for the Table 1 state and its perturbations.
DEFAULT_RHO = _PHYSICAL["rho"]


@functools.lru_cache(maxsize=16)
def fastmpc3d_params(obstacles: bool = True, rho=DEFAULT_RHO) -> rv.Params:
    """The rendezvous family's parameters of ``fastmpc-3d`` (obstacles on or off)."""
    return rv.make_params(**{**_PHYSICAL, "obstacles_on": obstacles, "rho": rho})


def _first_step(params, x0, N, t=0.0):
    config = rv.Config(N=N)
    guidance = rv.init(params, config, x0)
    plan = rv.initial_plan(params, config, guidance, x0)
    ocp, _ = rv.ocp(params, config, guidance, x0, jnp.asarray(t, x0.dtype), plan)
    return ocp


def fastmpc3d_step(x, t: float, obstacles: bool = True, N: int = 30) -> OCP:
    """The ``fastmpc-3d`` OCP at state ``x`` and time ``t`` [s], keep-out rows linearised
    about the unforced drift of ``x`` (the first step is ``t = 0`` from the Table 1 state)."""
    x = jnp.asarray(x, dtype=float)
    return _first_step(fastmpc3d_params(obstacles, DEFAULT_RHO), x, N, t)


def fastmpc3d_first_step(x0=None, obstacles: bool = True, N: int = 30, rho=DEFAULT_RHO) -> OCP:
    """The first-step OCP of the ``fastmpc-3d`` scenario (paper 000 §IV.A, Table 1).

    CW at 705 km altitude, m = 6500 kg, ZOH at Ts = 15 s, Q = diag(1,1,1,100,100,100),
    R = diag(100,100,100), Q_f = DARE solution, |u_i| <= 20 N (6 hard box rows per stage),
    target / holding point at the origin. Two spherical keep-out zones (radii 20 m and 50 m,
    moving on straight lines) give 2 soft rows per stage on x_{t+1}, linearised about the
    chaser's unforced drift path from x0 (a straight line to the target as the guess runs
    through obstacle 1 and makes the hard QP infeasible); without ``obstacles`` the rows are
    masked off.

    Args:
        x0: (6,) chaser state [m, m/s]; default Table 1, (50, -1000, 10, 0, 0, 0).
        obstacles: keep-out rows active or not.
        N: horizon, default 30.
        rho: exact L1 penalty of the keep-out rows [per metre], one value or one per obstacle.
    """
    x0 = jnp.asarray(FASTMPC3D_X0 if x0 is None else x0, dtype=float)
    ocp = _first_step(fastmpc3d_params(obstacles, _hashable(rho)), x0, N)
    validate_ocp(ocp)
    return ocp


def _hashable(rho):
    return tuple(float(r) for r in rho) if hasattr(rho, "__len__") else float(rho)


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
    return jnp.asarray(FASTMPC3D_X0) + delta


def stack_ocps(ocps) -> OCP:
    """Stack a sequence of same-shape OCPs into one batched OCP (leading batch axis)."""
    return jax.tree.map(lambda *a: jnp.stack(a), *ocps)


def fastmpc3d_first_step_batch(x0s, obstacles: bool = True, N: int = 30, rho=DEFAULT_RHO) -> OCP:
    """Batched :func:`fastmpc3d_first_step` for states x0s (batch, 6): every field gains a
    leading batch axis (built with ``jax.vmap``)."""
    x0s = jnp.asarray(x0s, dtype=float)
    if x0s.ndim != 2 or x0s.shape[1] != 6:
        raise ValueError(f"x0s must have shape (batch, 6), got {x0s.shape}")
    if not bool(jnp.all(jnp.isfinite(x0s))):
        raise ValueError("x0s must be finite")
    return _batch_builder(N)(fastmpc3d_params(obstacles, _hashable(rho)), x0s)


@functools.lru_cache(maxsize=8)
def _batch_builder(N: int):
    return jax.jit(jax.vmap(lambda p, x: _first_step(p, x, N), in_axes=(None, 0)))
