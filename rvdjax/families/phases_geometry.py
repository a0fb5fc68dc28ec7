"""The three-phase family's geometry (paper 003 Ch. 3): the rotating target's port and
approach axis, the keep-out planes' turn towards the cone axis (Eq. 3.6) and the approach
cone's slack."""

from __future__ import annotations

import jax.numpy as jnp

from rvdjax.constraints import approach_cone
from rvdjax.families.phases_inputs import POS, Params


def _rot_z(angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    z, o = jnp.zeros_like(angle), jnp.ones_like(angle)
    return jnp.stack(
        [jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2
    )


def target_state(p: Params, times):
    """Port position, port velocity and unit approach axis (..., 3) at the given times."""
    Rz = _rot_z(p.target_angle0 + p.target_rate * times)
    port = Rz @ p.port_body
    axis = Rz @ p.axis_body
    omega = jnp.array([0.0, 0.0, 1.0]) * p.target_rate
    return port, jnp.cross(jnp.broadcast_to(omega, port.shape), port), axis


def _turn(r0, a_final, n_real, ts, rate_max, v0, turn=None):
    """The keep-out planes' turn from the bearing of r0 towards a_final (paper 003
    Sec. 3.1.3): (u0, w, delta, fits), the unit bearing, the unit direction the normal leaves
    it in, the angle to turn [rad] and whether that fits in the horizon at rate_max.

    When the rotation fits in the horizon at the capped rate it follows the shortest great
    circle; otherwise "in the direction most closely aligned with the natural relative orbit
    motion" — here the sense in which the chaser's bearing turns, r0 x v0 (the long way round
    if that is the sense of motion). ``turn`` (``Config.latch_turn``): a latched rotation
    axis (zero: undecided); while it is set and the rotation does not fit, the planes keep
    turning about it instead. Antipodal bearings fall back to the plane through the radial
    axis.
    """
    u0 = r0 / jnp.maximum(jnp.linalg.norm(r0), 1e-12)
    cosd = jnp.clip(jnp.dot(u0, a_final), -1.0, 1.0)
    delta = jnp.arccos(cosd)
    w = a_final - cosd * u0
    alt = jnp.array([1.0, 0.0, 0.0]) - jnp.dot(u0, jnp.array([1.0, 0.0, 0.0])) * u0
    w = jnp.where(jnp.linalg.norm(w) > 1e-9, w, alt)
    w = w / jnp.maximum(jnp.linalg.norm(w), 1e-12)
    fits = delta <= rate_max * ts * n_real
    # bearing rate direction: the tangential part of v0; against w means the long way
    against = jnp.dot(v0 - jnp.dot(v0, u0) * u0, w) < 0.0
    if turn is not None:
        # latched: the long way when the shortest turn's axis u0 x w opposes the latched one
        latched = jnp.dot(turn, turn) > 0.0
        against = jnp.where(latched, jnp.dot(jnp.cross(u0, w), turn) < 0.0, against)
    long_way = ~fits & against
    w = jnp.where(long_way, -w, w)
    delta = jnp.where(long_way, 2.0 * jnp.pi - delta, delta)
    return u0, w, delta, fits


def _plane_normals(r0, a_final, N_max, n_real, ts, rate_max, v0, turn=None):
    """Keep-out plane normals (N_max, 3) rotating from the bearing of r0 towards a_final
    (paper 003 Eq. 3.6): equal angles over the real horizon, at most rate_max ts per stage,
    in the sense of :func:`_turn`."""
    u0, w, delta, _ = _turn(r0, a_final, n_real, ts, rate_max, v0, turn)
    step = jnp.minimum(delta / n_real, rate_max * ts)
    i = jnp.minimum(jnp.arange(1, N_max + 1), n_real)
    ang = jnp.minimum(delta, step * i)
    return jnp.cos(ang)[:, None] * u0 + jnp.sin(ang)[:, None] * w


def _in_cone(p: Params, r, t, n_faces):
    """Smallest approach-cone row slack of position r at time t (>= 0: inside)."""
    _, _, axis = target_state(p, t)
    b = approach_cone(jnp.zeros((1, 3)), axis[None], p.half_angle[0], n_faces, 6, POS)
    return jnp.min(b.f[0] - b.F[0, :, :3] @ r)
