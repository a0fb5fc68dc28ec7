"""Nonlinear relative-motion truth propagator (two-body, optionally J2) with fixed-step RK4.

Used for model mismatch in the closed loop (DESIGN.md §4; paper 003 Ch. 5 ran its truth model in
the 42 simulator with degree-8 gravity and flat-plate atmospheric drag — here the dominant zonal
term J2 and cannonball drag with an exponential atmosphere, :class:`Drag`).

Frames and conventions (same as :mod:`rvdjax.dynamics`):

* Inertial frame: Earth-centred inertial (ECI), z along the Earth's spin axis (the J2 axis).
* LVLH frame of the target: x along r_t (radial, outward), z along h = r_t x v_t (orbit normal,
  cross-track), y = z x x (along-track for a circular orbit). The rotation matrix
  ``R = [x_hat, y_hat, z_hat]`` (columns) maps LVLH components to ECI components.
* Frame angular velocity: ``omega = h / |r_t|^2`` (ECI). This is the exact LVLH angular velocity
  for two-body motion; with J2 the true frame also rotates slowly about x_hat
  (omega_x = |r| (a . h_hat) / |h|), which is deliberately ignored in the velocity transform (it is
  a definition of the relative velocity, used consistently in both directions).
* Relative state ``x_rel = (x, y, z, vx, vy, vz)`` [m, m/s]: position ``R^T (r_c - r_t)`` and
  velocity ``R^T (v_c - v_t - omega x (r_c - r_t))``, i.e. the velocity seen in the rotating frame.

Integration: both bodies are integrated with the same classical RK4 scheme in the inertial
frame. Internally the chaser is carried as its inertial offset ``(dr, dv) = (r_c - r_t,
v_c - v_t)``; because RK4 is invariant under linear changes of variables this is exactly the RK4
solution for the two bodies, but it avoids the cancellation error (~1e-9 m) of subtracting two
~7e6 m position vectors, so metre-level relative motion is resolved to ~1e-13 m.

Thrust: the force is given in the LVLH frame at the start of the interval and held constant *in
the rotating LVLH frame* (zero-order hold in LVLH, like the CW ZOH model of
:func:`rvdjax.dynamics.discretize_zoh`): at every RK4 stage it is rotated to ECI with the LVLH
basis of that stage's target state. The chaser mass is constant over the interval (no propellant
depletion). The target flies a free orbit (no thrust).

Everything is pure JAX, float64, and works under ``jax.jit``, ``jax.vmap`` and ``jax.grad``.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.dynamics import MU_EARTH, R_EARTH, check_finite, check_positive

__all__ = [
    "J2_EARTH",
    "OMEGA_EARTH",
    "Drag",
    "atmosphere_density",
    "drag_accel",
    "Orbit",
    "circular_orbit",
    "lvlh_basis",
    "lvlh_to_inertial",
    "inertial_to_lvlh",
    "accel",
    "propagate_relative",
    "propagate_step",
]

J2_EARTH = 1.08262668e-3  # Earth's second zonal harmonic (dimensionless)
OMEGA_EARTH = 7.292115e-5  # Earth's rotation rate [rad/s] (the atmosphere co-rotates)

# Exponential atmosphere (Vallado, "Fundamentals of Astrodynamics and Applications", Table 8-4,
# after CIRA-72): base altitude [km], density at the base [kg/m^3], scale height [km].
_ATMOSPHERE = (
    (0.0, 1.225, 7.249),
    (25.0, 3.899e-2, 6.349),
    (30.0, 1.774e-2, 6.682),
    (40.0, 3.972e-3, 7.554),
    (50.0, 1.057e-3, 8.382),
    (60.0, 3.206e-4, 7.714),
    (70.0, 8.770e-5, 6.549),
    (80.0, 1.905e-5, 5.799),
    (90.0, 3.396e-6, 5.382),
    (100.0, 5.297e-7, 5.877),
    (110.0, 9.661e-8, 7.263),
    (120.0, 2.438e-8, 9.473),
    (130.0, 8.484e-9, 12.636),
    (140.0, 3.845e-9, 16.149),
    (150.0, 2.070e-9, 22.523),
    (180.0, 5.464e-10, 29.740),
    (200.0, 2.789e-10, 37.105),
    (250.0, 7.248e-11, 45.546),
    (300.0, 2.418e-11, 53.628),
    (350.0, 9.518e-12, 53.298),
    (400.0, 3.725e-12, 58.515),
    (450.0, 1.585e-12, 60.828),
    (500.0, 6.967e-13, 63.822),
    (600.0, 1.454e-13, 71.835),
    (700.0, 3.614e-14, 88.667),
    (800.0, 1.170e-14, 124.64),
    (900.0, 5.245e-15, 181.05),
    (1000.0, 3.019e-15, 268.00),
)


class Drag(NamedTuple):
    """Cannonball drag of both bodies: a = -1/2 rho(h) B |v_rel| v_rel, v_rel = v - w_E x r.

    Paper 003 Eq. 5.5 sums flat plates, 1/2 rho |v_rel|^2 C_D sum_j A_j max(cos theta_j, 0); with
    a fixed attitude that is a constant area A, so B = C_D A / m (the ballistic coefficient).
    Only the *difference* of the two bodies' drag moves the relative state.

    Attributes:
        b_chaser: C_D A / m of the chaser [m^2/kg].
        b_target: C_D A / m of the target [m^2/kg].
    """

    b_chaser: jax.Array
    b_target: jax.Array


def atmosphere_density(altitude_m):
    """Exponential-atmosphere density [kg/m^3] at ``altitude_m`` [m] (Vallado Table 8-4).

    rho = rho_0 exp(-(h - h_0) / H) with the band's base h_0; above 1000 km the last band is
    extended; below 0 km the sea-level value is used.
    """
    table = jnp.asarray(_ATMOSPHERE)
    h_km = jnp.maximum(jnp.asarray(altitude_m) / 1e3, 0.0)
    k = jnp.clip(jnp.searchsorted(table[:, 0], h_km, side="right") - 1, 0, table.shape[0] - 1)
    h0, rho0, scale = table[k, 0], table[k, 1], table[k, 2]
    return rho0 * jnp.exp(-(h_km - h0) / scale)


def drag_accel(r, v, b):
    """Drag acceleration [m/s^2] in ECI of a body at (r, v) with ballistic coefficient ``b``
    [m^2/kg] in an atmosphere rotating with the Earth (about ECI z)."""
    v_rel = v - jnp.cross(jnp.array([0.0, 0.0, OMEGA_EARTH]), r)
    rho = atmosphere_density(jnp.linalg.norm(r) - R_EARTH)
    return -0.5 * rho * b * jnp.linalg.norm(v_rel) * v_rel


class Orbit(NamedTuple):
    """Inertial (ECI) state of the target.

    Attributes:
        r: position (3,) [m].
        v: velocity (3,) [m/s].
    """

    r: jax.Array
    v: jax.Array


def circular_orbit(altitude_m, inclination_rad=0.0, raan_rad=0.0, arg_lat_rad=0.0) -> Orbit:
    """Target on a circular two-body orbit.

    Args:
        altitude_m: altitude above R_EARTH [m], > 0 (radius a = R_EARTH + altitude).
        inclination_rad: inclination i [rad].
        raan_rad: right ascension of the ascending node Omega [rad].
        arg_lat_rad: argument of latitude u (angle from the ascending node) [rad].

    Returns:
        Orbit with |r| = a and |v| = sqrt(mu / a), v perpendicular to r (prograde).
    """
    check_positive("altitude_m", altitude_m, "m")
    f = partial(jnp.asarray, dtype=float)
    return _circular_orbit(f(altitude_m), f(inclination_rad), f(raan_rad), f(arg_lat_rad))


@jax.jit  # one compile instead of one per eager op (rvdjax.dynamics._mean_motion)
def _circular_orbit(altitude_m, i, raan, u) -> Orbit:
    a = R_EARTH + altitude_m
    # Unit vectors: P toward the ascending node, Q 90 deg ahead in the orbit plane.
    p = jnp.stack([jnp.cos(raan), jnp.sin(raan), jnp.zeros_like(raan)])
    q = jnp.stack([-jnp.sin(raan) * jnp.cos(i), jnp.cos(raan) * jnp.cos(i), jnp.sin(i)])
    speed = jnp.sqrt(MU_EARTH / a)
    r = a * (jnp.cos(u) * p + jnp.sin(u) * q)
    v = speed * (-jnp.sin(u) * p + jnp.cos(u) * q)
    return Orbit(r, v)


def lvlh_basis(r_t, v_t):
    """LVLH rotation and angular velocity of the target frame.

    Args:
        r_t: target position (3,) [m].
        v_t: target velocity (3,) [m/s].

    Returns:
        (R (3, 3), omega (3,)): R has columns (x_hat, y_hat, z_hat) in ECI, so that
        ``v_eci = R @ v_lvlh``; omega = (r_t x v_t) / |r_t|^2 [rad/s] in ECI.
    """
    h = jnp.cross(r_t, v_t)
    r2 = jnp.dot(r_t, r_t)
    x_hat = r_t / jnp.sqrt(r2)
    z_hat = h / jnp.linalg.norm(h)
    y_hat = jnp.cross(z_hat, x_hat)
    R = jnp.stack([x_hat, y_hat, z_hat], axis=1)
    return R, h / r2


def _lvlh_to_offset(orbit: Orbit, x_rel):
    """LVLH relative state -> inertial offset (r_c - r_t, v_c - v_t)."""
    R, omega = lvlh_basis(orbit.r, orbit.v)
    dr = R @ x_rel[:3]
    dv = R @ x_rel[3:] + jnp.cross(omega, dr)
    return dr, dv


def _offset_to_lvlh(orbit: Orbit, dr, dv):
    """Inertial offset (r_c - r_t, v_c - v_t) -> LVLH relative state (6,)."""
    R, omega = lvlh_basis(orbit.r, orbit.v)
    return jnp.concatenate([R.T @ dr, R.T @ (dv - jnp.cross(omega, dr))])


def lvlh_to_inertial(orbit: Orbit, x_rel):
    """Chaser inertial state from its LVLH state relative to the target.

    Args:
        orbit: target inertial state.
        x_rel: (6,) LVLH relative state (x, y, z, vx, vy, vz) [m, m/s].

    Returns:
        (r_c (3,), v_c (3,)) [m, m/s] in ECI:
        r_c = r_t + R p, v_c = v_t + R w + omega x (R p), with (p, w) = x_rel.
    """
    x_rel = jnp.asarray(x_rel, dtype=float)
    dr, dv = _lvlh_to_offset(orbit, x_rel)
    return orbit.r + dr, orbit.v + dv


def inertial_to_lvlh(orbit: Orbit, r_c, v_c):
    """LVLH relative state of a chaser given in ECI (inverse of :func:`lvlh_to_inertial`).

    Args:
        orbit: target inertial state.
        r_c: chaser position (3,) [m].
        v_c: chaser velocity (3,) [m/s].

    Returns:
        (6,) x_rel = (R^T (r_c - r_t), R^T (v_c - v_t - omega x (r_c - r_t))).
    """
    return _offset_to_lvlh(orbit, jnp.asarray(r_c) - orbit.r, jnp.asarray(v_c) - orbit.v)


def accel(r, j2: bool = False):
    """Gravitational acceleration in ECI: two-body plus (optionally) the J2 zonal term.

    ```text
    a = -mu r / |r|^3
        - (3/2) J2 mu Re^2 / |r|^5 * (x (1 - 5 z^2/|r|^2), y (1 - 5 z^2/|r|^2), z (3 - 5 z^2/|r|^2))
    ```

    Args:
        r: position (3,) [m] (ECI, z along the Earth's spin axis).
        j2: include J2 (static Python bool).

    Returns:
        (3,) acceleration [m/s^2].
    """
    r2 = jnp.dot(r, r)
    rn = jnp.sqrt(r2)
    a = -MU_EARTH / (r2 * rn) * r
    if j2:
        zz = r[2] ** 2 / r2
        k = -1.5 * J2_EARTH * MU_EARTH * R_EARTH**2 / (r2 * r2 * rn)
        a = a + k * jnp.stack(
            [r[0] * (1.0 - 5.0 * zz), r[1] * (1.0 - 5.0 * zz), r[2] * (3.0 - 5.0 * zz)]
        )
    return a


@partial(jax.jit, static_argnames=("n_substeps", "j2"))
def propagate_step(orbit, x_rel, force_lvlh, mass, dt, n_substeps, j2, drag: Drag | None = None):
    """:func:`propagate_relative` without the input checks (for use inside jitted loops)."""
    rt = jnp.asarray(orbit.r, dtype=float)
    vt = jnp.asarray(orbit.v, dtype=float)
    x_rel = jnp.asarray(x_rel, dtype=float)
    f_over_m = jnp.asarray(force_lvlh, dtype=float) / mass
    dr, dv = _lvlh_to_offset(Orbit(rt, vt), x_rel)
    h = jnp.asarray(dt, dtype=float) / n_substeps

    def deriv(s):
        rt, vt, dr, dv = s
        at = accel(rt, j2)
        R, _ = lvlh_basis(rt, vt)  # thrust held constant in the (rotating) LVLH frame
        da = accel(rt + dr, j2) - at + R @ f_over_m
        if drag is not None:
            a_dt = drag_accel(rt, vt, drag.b_target)
            at = at + a_dt
            da = da + drag_accel(rt + dr, vt + dv, drag.b_chaser) - a_dt
        return (vt, at, dv, da)

    def axpy(s, k, c):
        return tuple(si + c * ki for si, ki in zip(s, k, strict=True))

    def step(s, _):
        k1 = deriv(s)
        k2 = deriv(axpy(s, k1, 0.5 * h))
        k3 = deriv(axpy(s, k2, 0.5 * h))
        k4 = deriv(axpy(s, k3, h))
        s_new = tuple(
            si + (h / 6.0) * (a + 2.0 * b + 2.0 * c + d)
            for si, a, b, c, d in zip(s, k1, k2, k3, k4, strict=True)
        )
        return s_new, None

    (rt, vt, dr, dv), _ = jax.lax.scan(step, (rt, vt, dr, dv), None, length=n_substeps)
    orbit_next = Orbit(rt, vt)
    return orbit_next, _offset_to_lvlh(orbit_next, dr, dv)


def propagate_relative(
    orbit: Orbit, x_rel, force_lvlh, mass, dt, n_substeps: int, j2=False, drag: Drag | None = None
):
    """Propagate target and chaser over ``dt`` with fixed-step RK4 in the inertial frame.

    Args:
        orbit: target inertial state at the start of the interval (free orbit, no thrust).
        x_rel: (6,) chaser LVLH relative state [m, m/s] at the start of the interval.
        force_lvlh: (3,) chaser thrust force [N] in LVLH at the start of the interval, held
            constant in the rotating LVLH frame over the interval (rotated with the frame at
            every RK4 stage; matches the ZOH assumption of the CW model).
        mass: chaser mass [kg], > 0 (constant over the interval).
        dt: interval [s], > 0.
        n_substeps: number of RK4 steps of length dt / n_substeps (static int >= 1). For LEO,
            dt / n_substeps <= ~15 s gives relative-state errors far below 1e-6 m per step.
        j2: include the J2 zonal perturbation for both bodies (static bool).
        drag: atmospheric drag of both bodies (:class:`Drag`), or None (no drag).

    Returns:
        (orbit_next, x_rel_next): the target inertial state and the chaser relative state in
        the LVLH frame of orbit_next, both at t + dt.

    Raises:
        ValueError: if n_substeps is not a positive int, or concrete mass / dt are not finite
            and > 0, or concrete inputs are not finite.
    """
    if isinstance(n_substeps, bool) or not isinstance(n_substeps, int) or n_substeps < 1:
        raise ValueError(f"n_substeps must be a Python int >= 1 (static), got {n_substeps!r}")
    check_positive("mass", mass, "kg")
    check_positive("dt", dt, "s")
    check_finite("x_rel", x_rel)
    check_finite("force_lvlh", force_lvlh)
    check_finite("orbit.r", orbit.r)
    check_finite("orbit.v", orbit.v)
    if drag is not None:
        for name, b in (("drag.b_chaser", drag.b_chaser), ("drag.b_target", drag.b_target)):
            if not (np.isfinite(b) and b >= 0):
                raise ValueError(f"{name} (C_D A / m) must be finite and >= 0 m^2/kg, got {b}")
    return propagate_step(
        orbit, x_rel, force_lvlh, mass, dt, n_substeps=n_substeps, j2=bool(j2), drag=drag
    )
