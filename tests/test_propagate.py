"""Tests of the nonlinear (two-body / J2) RK4 truth propagator in :mod:`rvdjax.propagate`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from scipy.integrate import solve_ivp

import rvdjax  # noqa: F401  (float64)
from rvdjax.dynamics import MU_EARTH, R_EARTH, cw_continuous, discretize_zoh, mean_motion
from rvdjax.propagate import (
    J2_EARTH,
    OMEGA_EARTH,
    Drag,
    Orbit,
    _lvlh_to_offset,
    _offset_to_lvlh,
    accel,
    atmosphere_density,
    circular_orbit,
    inertial_to_lvlh,
    lvlh_to_inertial,
    propagate_relative,
)

ALT = 400e3  # [m]
MASS = 500.0  # [kg]
TS = 15.0  # [s]
ORBIT = circular_orbit(ALT, inclination_rad=0.9, raan_rad=0.3, arg_lat_rad=0.2)
# A generic relative state: unit position direction plus a drift-sized velocity (per metre).
_D = np.array([0.6, -0.7, 0.4, 0.3e-3, -0.5e-3, 0.2e-3])
DIR = _D / np.linalg.norm(_D[:3])


def _run(orbit, x, n_steps, n_substeps=1, j2=False, force=(0.0, 0.0, 0.0)):
    for _ in range(n_steps):
        orbit, x = propagate_relative(orbit, x, jnp.asarray(force), MASS, TS, n_substeps, j2=j2)
    return orbit, x


def _np_accel(r, j2):
    r = np.asarray(r)
    rn = np.linalg.norm(r)
    a = -MU_EARTH * r / rn**3
    if j2:
        zz = (r[2] / rn) ** 2
        k = -1.5 * J2_EARTH * MU_EARTH * R_EARTH**2 / rn**5
        a = a + k * np.array([r[0] * (1 - 5 * zz), r[1] * (1 - 5 * zz), r[2] * (3 - 5 * zz)])
    return a


def _scipy_two_bodies(orbit, x_rel, t_end, j2):
    """Reference: both bodies integrated in ECI by DOP853 (independent numpy gravity)."""
    rc, vc = lvlh_to_inertial(orbit, x_rel)
    y0 = np.concatenate([orbit.r, orbit.v, rc, vc])

    def f(_, y):
        return np.concatenate([y[3:6], _np_accel(y[0:3], j2), y[9:12], _np_accel(y[6:9], j2)])

    sol = solve_ivp(f, (0.0, t_end), y0, method="DOP853", rtol=1e-12, atol=1e-9)
    assert sol.success
    return sol.y[:, -1]


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------


def test_circular_orbit():
    rn = np.linalg.norm(ORBIT.r)
    assert rn == pytest.approx(R_EARTH + ALT, rel=1e-14)
    assert np.linalg.norm(ORBIT.v) == pytest.approx(np.sqrt(MU_EARTH / rn), rel=1e-14)
    assert abs(np.dot(ORBIT.r, ORBIT.v)) < 1e-14 * rn * np.linalg.norm(ORBIT.v)
    h = np.cross(ORBIT.r, ORBIT.v)
    assert np.arccos(h[2] / np.linalg.norm(h)) == pytest.approx(0.9, abs=1e-12)


def test_lvlh_axes():
    # Pure radial offset -> chaser farther out along r_t; y along v_t for a circular orbit.
    rc, _ = lvlh_to_inertial(ORBIT, jnp.array([10.0, 0, 0, 0, 0, 0]))
    np.testing.assert_allclose(rc - ORBIT.r, 10.0 * ORBIT.r / np.linalg.norm(ORBIT.r), atol=1e-8)
    rc, _ = lvlh_to_inertial(ORBIT, jnp.array([0, 10.0, 0, 0, 0, 0]))
    np.testing.assert_allclose(rc - ORBIT.r, 10.0 * ORBIT.v / np.linalg.norm(ORBIT.v), atol=1e-8)
    # A co-rotating point (zero LVLH velocity) has v_c - v_t = omega x dr.
    n = float(mean_motion(altitude_m=ALT))
    _, vc = lvlh_to_inertial(ORBIT, jnp.array([0, 10.0, 0, 0, 0, 0]))
    assert np.linalg.norm(vc - ORBIT.v) == pytest.approx(10.0 * n, rel=1e-9)


@pytest.mark.parametrize("scale", [1e-3, 10.0, 1e4])
def test_round_trip(scale):
    x = jnp.asarray(DIR * scale)
    # Offset form (what the propagator uses internally): exact to rounding of x itself.
    dr, dv = _lvlh_to_offset(ORBIT, x)
    np.testing.assert_allclose(_offset_to_lvlh(ORBIT, dr, dv), x, rtol=0, atol=1e-12 * scale)
    # Through absolute ECI vectors: limited by float64 rounding of |r| ~ 6.8e6 m (~1e-9 m).
    back = inertial_to_lvlh(ORBIT, *lvlh_to_inertial(ORBIT, x))
    r_abs = np.linalg.norm(ORBIT.r)
    tol = 1e-12 * scale + 8 * np.finfo(float).eps * r_abs
    np.testing.assert_allclose(back[:3], x[:3], rtol=0, atol=tol)
    np.testing.assert_allclose(back[3:], x[3:], rtol=0, atol=1e-12 * scale + 1e-11)
    # Inverse direction, relative to the magnitude of the ECI vectors: 1e-12.
    rc, vc = lvlh_to_inertial(ORBIT, x)
    rc2, vc2 = lvlh_to_inertial(ORBIT, inertial_to_lvlh(ORBIT, rc, vc))
    np.testing.assert_allclose(rc2, rc, rtol=1e-12)
    np.testing.assert_allclose(vc2, vc, rtol=1e-12)


# --------------------------------------------------------------------------------------------
# Nonlinear vs CW
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n_steps", [1, 40])  # one Ts = 15 s and 10 minutes
def test_matches_cw_with_quadratic_error(n_steps):
    n = mean_motion(altitude_m=ALT)
    Ad, _ = discretize_zoh(*cw_continuous(n, MASS), TS)
    errs = []
    for s in (10.0, 100.0, 1000.0):
        x0 = jnp.asarray(DIR * s)
        _, x = _run(ORBIT, x0, n_steps)
        xc = x0
        for _ in range(n_steps):
            xc = Ad @ xc
        errs.append(float(np.linalg.norm(np.asarray(x - xc)[:3])))
    # Leading nonlinear relative acceleration ~ (3/2) n^2 rho^2 / r; position error ~ a t^2 / 2.
    t = n_steps * TS
    r = R_EARTH + ALT
    for s, e in zip((10.0, 100.0, 1000.0), errs, strict=True):
        bound = 3.0 * float(n) ** 2 * s**2 / r * t**2
        assert e < bound, (s, e, bound)
        assert e > 1e-3 * bound  # the mismatch is real, not rounding
    # Second-order scaling: 10x separation -> ~100x error.
    assert 70.0 < errs[1] / errs[0] < 140.0, errs
    assert 70.0 < errs[2] / errs[1] < 140.0, errs


def test_thrust_matches_cw_zoh():
    """LVLH-held thrust over one Ts agrees with the CW ZOH input model to second order."""
    n = mean_motion(altitude_m=ALT)
    Ad, Bd = discretize_zoh(*cw_continuous(n, MASS), TS)
    F = jnp.array([0.5, -0.3, 0.2])
    x0 = jnp.asarray(DIR * 10.0)
    _, x = propagate_relative(ORBIT, x0, F, MASS, TS, 1)
    err = np.linalg.norm(np.asarray(x - (Ad @ x0 + Bd @ F)))
    assert err < 1e-7 * np.linalg.norm(np.asarray(Bd @ F)) + 1e-8


def test_thrust_delta_v():
    F = jnp.array([0.4, -0.2, 0.3])
    dt = 0.5
    x0 = jnp.asarray(DIR * 50.0)
    _, x_f = propagate_relative(ORBIT, x0, F, MASS, dt, 2)
    _, x_0 = propagate_relative(ORBIT, x0, jnp.zeros(3), MASS, dt, 2)
    dv = np.asarray(x_f - x_0)[3:]
    expected = np.asarray(F) * dt / MASS
    # Corrections are O(n dt) ~ 1e-3 relative (Coriolis / frame rotation).
    np.testing.assert_allclose(dv, expected, rtol=0, atol=2e-3 * np.linalg.norm(expected))
    # Position change ~ F dt^2 / (2 m).
    dp = np.asarray(x_f - x_0)[:3]
    np.testing.assert_allclose(
        dp, 0.5 * expected * dt, rtol=0, atol=3e-3 * np.linalg.norm(expected)
    )


# --------------------------------------------------------------------------------------------
# Accuracy against scipy, J2
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("j2", [False, True])
def test_matches_scipy(j2):
    x0 = jnp.asarray(DIR * 1000.0)
    n_steps = 40  # 10 minutes, RK4 step 5 s
    orbit, x = _run(ORBIT, x0, n_steps, n_substeps=3, j2=j2)
    y = _scipy_two_bodies(ORBIT, x0, n_steps * TS, j2)
    np.testing.assert_allclose(orbit.r, y[0:3], rtol=0, atol=1e-4)
    np.testing.assert_allclose(orbit.v, y[3:6], rtol=0, atol=1e-7)
    x_ref = np.asarray(
        inertial_to_lvlh(Orbit(jnp.asarray(y[0:3]), jnp.asarray(y[3:6])), y[6:9], y[9:12])
    )
    # Relative state from differences of scipy's absolute states (rounding ~1e-8 m).
    np.testing.assert_allclose(x[:3], x_ref[:3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(x[3:], x_ref[3:], rtol=0, atol=1e-9)


def test_j2_effect_plausible():
    x0 = jnp.asarray(DIR * 100.0)
    o0, x_0 = _run(ORBIT, x0, 1, n_substeps=3)
    o2, x_2 = _run(ORBIT, x0, 1, n_substeps=3, j2=True)
    # Target: J2 acceleration (~1e-2 m/s^2 in LEO) displaces it by ~ a dt^2 / 2 over one step.
    a_j2 = np.linalg.norm(np.asarray(accel(ORBIT.r, True) - accel(ORBIT.r, False)))
    assert 5e-3 < a_j2 < 2e-2
    d = np.linalg.norm(np.asarray(o2.r - o0.r))
    assert d == pytest.approx(0.5 * a_j2 * TS**2, rel=0.05)
    # Relative state: a small but non-zero change.
    dx = np.linalg.norm(np.asarray(x_2 - x_0))
    assert 1e-7 < dx < 1e-2


def test_j2_energy_conserved():
    """Without thrust, two-body + J2 energy (zonal => time-invariant potential) is conserved."""

    def energy(r, v, j2):
        r = np.asarray(r)
        rn = np.linalg.norm(r)
        u = -MU_EARTH / rn
        if j2:
            s2 = (r[2] / rn) ** 2
            u += MU_EARTH / rn * J2_EARTH * (R_EARTH / rn) ** 2 * 0.5 * (3 * s2 - 1)
        return 0.5 * float(np.dot(v, v)) + u

    x0 = jnp.asarray(DIR * 100.0)
    orbit, x = _run(ORBIT, x0, 40, n_substeps=3, j2=True)
    e0, e1 = energy(ORBIT.r, ORBIT.v, True), energy(orbit.r, orbit.v, True)
    assert abs(e1 - e0) < 1e-11 * abs(e0)
    rc0, vc0 = lvlh_to_inertial(ORBIT, x0)
    rc1, vc1 = lvlh_to_inertial(orbit, x)
    assert abs(energy(rc1, vc1, True) - energy(rc0, vc0, True)) < 1e-11 * abs(e0)
    # ...whereas the pure two-body energy does change (J2 does work along the orbit).
    assert abs(energy(orbit.r, orbit.v, False) - energy(ORBIT.r, ORBIT.v, False)) > 1e-6 * abs(e0)


# --------------------------------------------------------------------------------------------
# JAX transformations
# --------------------------------------------------------------------------------------------


def test_jit_vmap_batch():
    rng = np.random.default_rng(0)
    xs = jnp.asarray(rng.normal(size=(8, 6)) * np.array([100, 100, 100, 0.1, 0.1, 0.1]))
    fs = jnp.asarray(rng.normal(size=(8, 3)))

    @jax.jit
    def batch(orbit, xs, fs):
        return jax.vmap(lambda x, f: propagate_relative(orbit, x, f, MASS, TS, 3, j2=True))(xs, fs)

    orbits, out = batch(ORBIT, xs, fs)
    assert out.shape == (8, 6) and orbits.r.shape == (8, 3)
    for i in range(8):
        o, xi = propagate_relative(ORBIT, xs[i], fs[i], MASS, TS, 3, j2=True)
        np.testing.assert_allclose(out[i], xi, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(
            orbits.r[i], o.r, rtol=1e-14, atol=1e-14 * np.linalg.norm(np.asarray(o.r))
        )


def test_grad_matches_central_differences():
    @jax.jit
    def loss(x):
        _, xn = propagate_relative(ORBIT, x, jnp.array([0.1, 0.0, -0.1]), MASS, 60.0, 4, j2=True)
        return jnp.linalg.norm(xn[:3])

    x0 = jnp.asarray(DIR * 100.0)
    g = np.asarray(jax.jit(jax.grad(loss))(x0))
    assert np.all(np.isfinite(g))
    steps = np.array([1e-2, 1e-2, 1e-2, 1e-5, 1e-5, 1e-5])
    fd = np.empty(6)
    for i in range(6):
        e = np.zeros(6)
        e[i] = steps[i]
        fd[i] = (float(loss(x0 + e)) - float(loss(x0 - e))) / (2 * steps[i])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


def test_input_validation():
    with pytest.raises(ValueError, match="n_substeps"):
        propagate_relative(ORBIT, jnp.zeros(6), jnp.zeros(3), MASS, TS, 0)
    with pytest.raises(ValueError, match="mass"):
        propagate_relative(ORBIT, jnp.zeros(6), jnp.zeros(3), -1.0, TS, 1)
    with pytest.raises(ValueError, match="dt"):
        propagate_relative(ORBIT, jnp.zeros(6), jnp.zeros(3), MASS, 0.0, 1)
    with pytest.raises(ValueError, match="x_rel"):
        propagate_relative(ORBIT, jnp.full(6, jnp.nan), jnp.zeros(3), MASS, TS, 1)


# --------------------------------------------------------------------------------------------
# Atmospheric drag
# --------------------------------------------------------------------------------------------


def test_atmosphere_density():
    # sea level: the standard 1.225 kg/m^3; bands join without jumps (< 3 %); density falls
    # monotonically with altitude; 500 km: 1e-13..1e-12 kg/m^3 (mean solar activity range)
    assert float(atmosphere_density(0.0)) == pytest.approx(1.225)
    h = np.linspace(0.0, 1000e3, 20001)
    rho = np.asarray(jax.vmap(atmosphere_density)(jnp.asarray(h)))
    assert np.all(np.diff(rho) < 0)
    assert np.max(np.abs(np.diff(np.log(rho)))) < 0.03
    assert 1e-13 < float(atmosphere_density(500e3)) < 1e-12


def _np_drag(r, v, b):
    v_rel = v - np.cross([0.0, 0.0, OMEGA_EARTH], r)
    rho = float(atmosphere_density(np.linalg.norm(r) - R_EARTH))
    return -0.5 * rho * b * np.linalg.norm(v_rel) * v_rel


def test_drag_matches_scipy_and_moves_the_chaser_as_cw_predicts():
    """Both bodies with J2 and drag against DOP853. A chaser with the smaller ballistic
    coefficient (paper 003 Sec. 5.4: C_D 1.4 vs 2.0) feels a net along-track push relative to
    the target; the motion is that of CW under a constant along-track acceleration (exact
    solution by scipy's expm of the augmented CW matrix)."""
    # 300 km, so that drag moves the relative state measurably within the test's 20 minutes
    orbit = circular_orbit(300e3, inclination_rad=0.9)
    drag = Drag(jnp.asarray(1.4 * 0.04 / 14.0), jnp.asarray(2.0 * 0.04 / 14.0))
    x0 = jnp.zeros(6)
    o, x = orbit, x0
    o_nd, x_nd = orbit, x0
    n_steps, dt = 40, 30.0
    for _ in range(n_steps):
        o, x = propagate_relative(o, x, jnp.zeros(3), 14.0, dt, 6, j2=True, drag=drag)
        o_nd, x_nd = propagate_relative(o_nd, x_nd, jnp.zeros(3), 14.0, dt, 6, j2=True)
    rc, vc = lvlh_to_inertial(orbit, x0)
    bt, bc = float(drag.b_target), float(drag.b_chaser)

    def f(_, y):
        return np.concatenate(
            [
                y[3:6],
                _np_accel(y[0:3], True) + _np_drag(y[0:3], y[3:6], bt),
                y[9:12],
                _np_accel(y[6:9], True) + _np_drag(y[6:9], y[9:12], bc),
            ]
        )

    y0 = np.concatenate([orbit.r, orbit.v, rc, vc])
    sol = solve_ivp(f, (0.0, n_steps * dt), y0, method="DOP853", rtol=1e-12, atol=1e-9)
    y = sol.y[:, -1]
    x_ref = np.asarray(
        inertial_to_lvlh(Orbit(jnp.asarray(y[0:3]), jnp.asarray(y[3:6])), y[6:9], y[9:12])
    )
    np.testing.assert_allclose(x[:3], x_ref[:3], rtol=0, atol=1e-5)
    assert np.all(np.abs(x_nd[:3]) < 1e-6)  # same orbit, no drag: no relative motion
    t = n_steps * dt
    a_rel = float(np.linalg.norm(_np_drag(np.asarray(orbit.r), np.asarray(orbit.v), bt - bc)))
    n = float(np.sqrt(MU_EARTH / np.linalg.norm(orbit.r) ** 3))
    M = np.zeros((7, 7))
    M[0:3, 3:6] = np.eye(3)
    M[3, 0], M[3, 4], M[4, 3], M[5, 2] = 3 * n**2, 2 * n, -2 * n, -(n**2)
    M[4, 6] = a_rel  # constant along-track push (state 7 = 1)
    x_cw = scipy.linalg.expm(M * t) @ np.r_[np.zeros(6), 1.0]
    assert x_cw[0] > 0 and x_cw[1] > 0  # above and ahead of the target
    np.testing.assert_allclose(np.asarray(x[:2]), x_cw[:2], rtol=0.1)
