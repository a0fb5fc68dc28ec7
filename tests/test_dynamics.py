"""Tests of rvdjax.dynamics against SciPy (expm, solve_ivp, solve_discrete_are)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl
from scipy.integrate import solve_ivp

import rvdjax  # noqa: F401  (enables x64)
from rvdjax.dynamics import (
    MU_EARTH,
    R_EARTH,
    cw_continuous,
    dare,
    discretize_impulsive,
    discretize_zoh,
    mean_motion,
    planar2dof_continuous,
    planar3dof_continuous,
    zoh_states,
)
from rvdjax.solver import stagewise as sw

MASS = 6500.0
TS = 15.0
Q_CW = np.diag([1.0, 1.0, 1.0, 100.0, 100.0, 100.0])
R_CW = np.diag([100.0, 100.0, 100.0])


@pytest.fixture(scope="module")
def n705():
    return float(mean_motion(altitude_m=705e3))


def cw_rhs_np(n, mass, u):
    """CW/Hill equations written out independently (x radial, y along-track)."""

    def f(_, s):
        x, y, z, vx, vy, vz = s
        return [
            vx,
            vy,
            vz,
            3 * n**2 * x + 2 * n * vy + u[0] / mass,
            -2 * n * vx + u[1] / mass,
            -(n**2) * z + u[2] / mass,
        ]

    return f


def test_mean_motion(n705):
    a = R_EARTH + 705e3
    assert n705 == pytest.approx(np.sqrt(MU_EARTH / a**3), rel=1e-15)
    assert float(mean_motion(semi_major_axis_m=a)) == pytest.approx(n705, rel=1e-15)
    # period of a 705 km orbit is about 98.8 min
    assert 2 * np.pi / n705 / 60 == pytest.approx(98.8, abs=0.1)


def test_cw_continuous_structure(n705):
    Ac, Bc = cw_continuous(n705, MASS)
    assert Ac.shape == (6, 6) and Bc.shape == (6, 3)
    s = np.array([1.0, 2.0, 3.0, 0.4, 0.5, 0.6])
    u = np.array([7.0, 8.0, 9.0])
    ref = cw_rhs_np(n705, MASS, u)(0, s)
    np.testing.assert_allclose(Ac @ s + Bc @ u, ref, rtol=1e-14, atol=1e-14 * np.linalg.norm(ref))


def test_zoh_matches_scipy_expm(n705):
    Ac, Bc = cw_continuous(n705, MASS)
    Ad, Bd = discretize_zoh(Ac, Bc, TS)
    M = np.zeros((9, 9))
    M[:6, :6], M[:6, 6:] = np.asarray(Ac), np.asarray(Bc)
    E = sl.expm(M * TS)
    # element-wise against a few ulps of the matrix's norm (its entries span decades)
    np.testing.assert_allclose(Ad, E[:6, :6], rtol=1e-13, atol=1e-13 * np.linalg.norm(E[:6, :6]))
    np.testing.assert_allclose(Bd, E[:6, 6:], rtol=1e-13, atol=1e-13 * np.linalg.norm(E[:6, 6:]))


@pytest.mark.parametrize("mv", [None, sw.mv], ids=["matmul", "multiply-and-sum"])
def test_zoh_states_match_scipy_expm(n705, mv):
    """The states between samples under a constant input (the power series by Horner's rule,
    with ``A @ x`` as on the CPU or the multiplies and sums a GPU program uses) are those of
    SciPy's expm of the augmented matrix, to 1e-13 relative, at taus up to a 60 s step."""
    Ac, Bc = cw_continuous(n705, MASS)
    rng = np.random.default_rng(4)
    x, u = rng.normal(size=6) * [100, 100, 100, 0.1, 0.1, 0.1], rng.normal(size=3)
    taus = np.array([1.0, 7.5, 30.0, 60.0])
    kwargs = {} if mv is None else {"mv": mv}
    got = zoh_states(Ac, Bc, jnp.asarray(x), jnp.asarray(u), jnp.asarray(taus), **kwargs)
    aug = np.zeros((9, 9))
    aug[:6, :6], aug[:6, 6:] = np.asarray(Ac), np.asarray(Bc)
    want = [(sl.expm(aug * t) @ np.concatenate([x, u]))[:6] for t in taus]
    np.testing.assert_allclose(np.asarray(got), np.stack(want), rtol=1e-13, atol=1e-13 * 100)


def test_zoh_matches_ode_with_constant_input(n705):
    Ac, Bc = cw_continuous(n705, MASS)
    ts = 60.0
    Ad, Bd = discretize_zoh(Ac, Bc, ts)
    x0 = np.array([50.0, -1000.0, 10.0, 0.1, -0.2, 0.05])
    u = np.array([20.0, -15.0, 5.0])
    sol = solve_ivp(cw_rhs_np(n705, MASS, u), (0, ts), x0, method="DOP853", rtol=1e-13, atol=1e-12)
    x1 = np.asarray(Ad @ x0 + Bd @ u)
    np.testing.assert_allclose(x1, sol.y[:, -1], rtol=1e-11, atol=1e-9)


def test_impulsive_matches_ode_with_velocity_jump(n705):
    Ac, _ = cw_continuous(n705, MASS)
    ts = 30.0
    Ad, Bd = discretize_impulsive(Ac, ts)
    assert Bd.shape == (6, 3)
    x0 = np.array([140.0, -1580.0, 60.0, -0.9, -0.32, 0.0])
    dv = np.array([0.3, -0.1, 0.05])
    start = x0 + np.concatenate([np.zeros(3), dv])
    sol = solve_ivp(
        cw_rhs_np(n705, MASS, np.zeros(3)),
        (0, ts),
        start,
        method="DOP853",
        rtol=1e-13,
        atol=1e-12,
    )
    np.testing.assert_allclose(np.asarray(Ad @ x0 + Bd @ dv), sol.y[:, -1], rtol=1e-11, atol=1e-9)
    Ad_v = np.asarray(Ad)[:, 3:]
    np.testing.assert_allclose(Bd, Ad_v, rtol=1e-14, atol=1e-14 * np.linalg.norm(Ad_v))


def test_planar_models_double_integrator():
    m, inertia, ts = 16.9478, 0.2709, 2.0
    Ac, Bc = planar3dof_continuous(m, inertia)
    Ad, Bd = discretize_zoh(Ac, Bc, ts)
    expected_Ad = np.block([[np.eye(3), ts * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
    inv = np.array([1 / m, 1 / m, 1 / inertia])
    expected_Bd = np.concatenate([np.diag(inv) * ts**2 / 2, np.diag(inv) * ts])
    np.testing.assert_allclose(Ad, expected_Ad, atol=1e-13 * np.linalg.norm(expected_Ad))
    np.testing.assert_allclose(
        Bd, expected_Bd, rtol=1e-13, atol=1e-13 * np.linalg.norm(expected_Bd)
    )
    Ac2, Bc2 = planar2dof_continuous(10.0)
    Ad2, Bd2 = discretize_zoh(Ac2, Bc2, 5.0)
    np.testing.assert_allclose(Ad2, [[1, 0, 5, 0], [0, 1, 0, 5], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.testing.assert_allclose(Bd2[:, 0], [25 / 20, 0, 0.5, 0], atol=1e-13 * np.hypot(1.25, 0.5))
    Adi, Bdi = discretize_impulsive(Ac2, 5.0)
    np.testing.assert_allclose(Bdi, [[5, 0], [0, 5], [1, 0], [0, 1]], atol=1e-13 * np.sqrt(52))


def test_dare_cw_matches_scipy(n705):
    Ad, Bd = discretize_zoh(*cw_continuous(n705, MASS), TS)
    # CW is marginally stable: eigenvalues of Ad on the unit circle
    assert np.max(np.abs(np.linalg.eigvals(np.asarray(Ad)))) == pytest.approx(1.0, abs=1e-12)
    P_ref = sl.solve_discrete_are(np.asarray(Ad), np.asarray(Bd), Q_CW, R_CW)
    P = np.asarray(dare(Ad, Bd, Q_CW, R_CW))
    assert np.min(np.diag(P)[3:]) > 1e6
    np.testing.assert_allclose(P, P_ref, rtol=1e-9, atol=1e-9 * np.max(np.abs(P_ref)))
    np.testing.assert_allclose(P, P.T, rtol=0, atol=1e-12 * np.max(np.abs(P)))
    # Riccati residual relative to ||P||
    A, B = np.asarray(Ad), np.asarray(Bd)
    res = A.T @ P @ A - A.T @ P @ B @ np.linalg.solve(R_CW + B.T @ P @ B, B.T @ P @ A) + Q_CW - P
    assert np.max(np.abs(res)) < 1e-12 * np.max(np.abs(P))


def test_dare_random_stabilizable():
    rng = np.random.default_rng(3)
    nx, nu = 5, 2
    A = rng.normal(size=(nx, nx)) * 0.6  # a few eigenvalues outside the unit circle
    A[0, 0] += 1.2
    assert np.max(np.abs(np.linalg.eigvals(A))) > 1.0
    B = rng.normal(size=(nx, nu))
    L = rng.normal(size=(nx, nx))
    Q = L @ L.T / nx + 0.1 * np.eye(nx)
    R = np.diag([0.5, 2.0])
    P_ref = sl.solve_discrete_are(A, B, Q, R)
    P = np.asarray(dare(A, B, Q, R))
    np.testing.assert_allclose(P, P_ref, rtol=1e-9, atol=1e-9 * np.max(np.abs(P_ref)))


def _central_diff(f, x, h):
    return (np.asarray(f(x + h)) - np.asarray(f(x - h))) / (2 * h)


def test_discretization_gradients_vs_finite_differences(n705):
    """Forward-mode derivatives of (Ad, Bd) [ZOH] and Bd [impulsive] w.r.t. ts, n, mass."""

    def mats(ts, n, m):
        Ac, Bc = cw_continuous(n, m)
        Ad, Bd = discretize_zoh(Ac, Bc, ts)
        return jnp.concatenate([Ad, Bd, discretize_impulsive(Ac, ts)[1]], axis=1)

    f = jax.jit(mats)
    J_ts, J_n, J_m = (np.asarray(J) for J in jax.jit(jax.jacfwd(mats, (0, 1, 2)))(TS, n705, MASS))
    fd_ts = _central_diff(lambda t: f(t, n705, MASS), TS, 1e-3)
    fd_n = _central_diff(lambda n: f(TS, n, MASS), n705, 1e-7)
    np.testing.assert_allclose(J_ts, fd_ts, rtol=1e-7, atol=1e-7 * np.max(np.abs(fd_ts)))
    np.testing.assert_allclose(J_n, fd_n, rtol=1e-7, atol=1e-7 * np.max(np.abs(fd_n)))
    M = np.asarray(f(TS, n705, MASS))
    # exact identity: d expm(Ac ts)/d ts = Ac expm(Ac ts)
    Ac, _ = cw_continuous(n705, MASS)
    dA = Ac @ M[:, :6]
    np.testing.assert_allclose(J_ts[:, :6], dA, rtol=1e-12, atol=1e-13 * np.linalg.norm(dA))
    # mass: the ZOH Bd is proportional to 1/mass; Ad and the impulsive Bd do not depend on it
    dB = -M[:, 6:9] / MASS
    np.testing.assert_allclose(J_m[:, 6:9], dB, rtol=1e-12, atol=1e-13 * np.linalg.norm(dB))
    assert np.all(J_m[:, :6] == 0) and np.all(J_m[:, 9:] == 0)


def test_dare_reverse_gradient_vs_finite_differences(n705):
    def cost(ts):
        Ad, Bd = discretize_zoh(*cw_continuous(n705, MASS), ts)
        return jnp.trace(dare(Ad, Bd, Q_CW, R_CW))

    g = float(jax.jit(jax.grad(cost))(TS))
    fd = float(_central_diff(cost, TS, 1e-3))
    assert g == pytest.approx(fd, rel=1e-6)


def test_jit_and_vmap_skip_validation(n705):
    Ac, Bc = cw_continuous(n705, MASS)
    f = jax.jit(lambda ts, n, m: discretize_zoh(*cw_continuous(n, m), ts))
    Ad, Bd = f(TS, n705, MASS)
    Ad0, Bd0 = discretize_zoh(Ac, Bc, TS)
    # element-wise against the matrix's norm: another CPU may round an entry near 0 otherwise
    np.testing.assert_allclose(Ad, Ad0, rtol=1e-14, atol=1e-14 * np.linalg.norm(Ad0))
    np.testing.assert_allclose(Bd, Bd0, rtol=1e-14, atol=1e-14 * np.linalg.norm(Bd0))
    Ads = jax.vmap(lambda ts: discretize_zoh(Ac, Bc, ts)[0])(jnp.array([5.0, 15.0]))
    np.testing.assert_allclose(Ads[1], Ad0, rtol=1e-14, atol=1e-14 * np.linalg.norm(Ad0))
    assert jnp.isfinite(jax.jit(lambda a: mean_motion(altitude_m=a))(705e3))


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: cw_continuous(1e-3, 0.0), "mass"),
        (lambda: cw_continuous(1e-3, -5.0), "mass"),
        (lambda: cw_continuous(1e-3, float("nan")), "mass"),
        (lambda: cw_continuous(0.0, 10.0), "n (mean motion)"),
        (lambda: cw_continuous(np.inf, 10.0), "n (mean motion)"),
        (lambda: planar3dof_continuous(10.0, 0.0), "inertia"),
        (lambda: planar3dof_continuous(-1.0, 0.2), "mass"),
        (lambda: planar2dof_continuous(np.array(-2.0)), "mass"),
        (lambda: discretize_zoh(np.eye(2), np.ones((2, 1)), 0.0), "ts"),
        (lambda: discretize_zoh(np.eye(2), np.ones((2, 1)), -1.0), "ts"),
        (lambda: discretize_zoh(np.eye(2), np.ones((2, 1)), float("nan")), "ts"),
        (lambda: discretize_zoh(np.full((2, 2), np.nan), np.ones((2, 1)), 1.0), "Ac"),
        (lambda: discretize_impulsive(np.eye(2), -3.0), "ts"),
        (lambda: mean_motion(), "altitude_m"),
        (lambda: mean_motion(700e3, 7e6), "semi_major_axis_m"),
        (lambda: mean_motion(altitude_m=-1.0), "altitude_m"),
        (lambda: mean_motion(semi_major_axis_m=float("nan")), "semi_major_axis_m"),
        (lambda: dare(np.eye(2), np.ones((2, 1)), np.eye(2), -np.eye(1)), "R"),
    ],
)
def test_bad_inputs_raise_value_error_naming_parameter(call, name):
    with pytest.raises(ValueError, match=name.replace("(", r"\(").replace(")", r"\)")):
        call()
