"""The navigation filter (rvdjax.loop.navigation, LoopConfig.nav_filter) and the time limit per
maneuver (LoopConfig.time_limit_s)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from rvdjax.disturbances import disturbances, gm_stationary_std
from rvdjax.loop import LoopConfig, RunStatus, fly
from rvdjax.loop.engine import EngineConfig, fly_batch
from rvdjax.loop.navigation import (
    Q_FLOOR,
    R_FLOOR,
    NavState,
    measurement_covariance,
    nav_init,
    nav_predict,
    nav_update,
    process_noise,
    thrust_error_fraction,
)
from rvdjax.scenarios import get_scenario

VBAR = get_scenario("thesis-vbar")
PARAMS, X0 = VBAR.build()
D = PARAMS.plant.disturbances  # paper 003: 5 cm, 1 mm/s per axis
LAYOUT = VBAR.guidance_family.layout


def _spd(rng, n, scale=1.0):
    M = rng.standard_normal((n, n))
    return scale * (M @ M.T + n * np.eye(n))


def test_filter_equations_match_the_textbook():
    """update / predict against NumPy's textbook Kalman filter (H = I) on random matrices."""
    rng = np.random.default_rng(0)
    nx, nu = 6, 3
    for _ in range(3):
        P, R, Qp = _spd(rng, nx), _spd(rng, nx, 0.1), _spd(rng, nx, 0.01)
        x, z = rng.standard_normal(nx), rng.standard_normal(nx)
        A, B, u = (
            rng.standard_normal((nx, nx)),
            rng.standard_normal((nx, nu)),
            rng.standard_normal(nu),
        )
        # update: K = P H^T (H P H^T + R)^-1, x+ = x + K (z - H x), P+ = (I - K H) P
        K = P @ np.linalg.inv(P + R)
        x_ref, P_ref = x + K @ (z - x), (np.eye(nx) - K) @ P
        up = nav_update(NavState(jnp.asarray(x), jnp.asarray(P)), jnp.asarray(z), jnp.asarray(R))
        np.testing.assert_allclose(up.x_hat, x_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(up.P, P_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_array_equal(up.P, np.asarray(up.P).T)
        # predict: x- = A x + B u, P- = A P A^T + Qp
        pr = nav_predict(up, jnp.asarray(A), jnp.asarray(B), jnp.asarray(u), jnp.asarray(Qp))
        np.testing.assert_allclose(pr.x_hat, A @ x_ref + B @ u, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(pr.P, A @ P_ref @ A.T + Qp, rtol=1e-10, atol=1e-12)
    # initialisation from the first measurement
    nav = nav_init(jnp.asarray(z), jnp.asarray(R))
    np.testing.assert_array_equal(nav.x_hat, z)
    np.testing.assert_array_equal(nav.P, R)


def test_noise_models():
    """R from the layout (floored where exact), s_w from the Gauss-Markov model (4.62 % for
    paper 003 Table 5.1, by the continuous Lyapunov equation), Qp = B diag((s_w u)^2) B^T +
    floor R."""
    R = np.asarray(measurement_covariance(LAYOUT, D))
    np.testing.assert_allclose(np.diag(R), [0.05**2] * 3 + [1e-3**2] * 3, rtol=1e-14)
    assert np.count_nonzero(R - np.diag(np.diag(R))) == 0
    # planar layout: (x, y, theta, vx, vy, omega); omega is not measured with noise
    planar = get_scenario("spot-2d-a").guidance_family.layout
    d = disturbances(sigma_att=0.01)
    np.testing.assert_allclose(
        np.diag(measurement_covariance(planar, d)),
        [0.05**2, 0.05**2, 1e-4, 1e-6, 1e-6, R_FLOOR],
        rtol=1e-14,
    )
    F = np.array([[-1.0 / float(D.tau), 1.0], [-(float(D.omega_n) ** 2), -2.0 * float(D.omega_n)]])
    GGT = np.diag([float(D.eta_w), float(D.eta_v)]) ** 2
    sigma = np.sqrt(scipy.linalg.solve_continuous_lyapunov(F, -GGT)[0, 0])
    for dt in (5.0, 30.0):
        assert float(gm_stationary_std(D, dt)) == pytest.approx(sigma, rel=1e-8)
    s_w = float(thrust_error_fraction(D, 30.0))
    assert s_w == pytest.approx(0.0462, abs=5e-5)
    B, u = np.asarray(PARAMS.B[0]), np.array([0.1, -0.05, 0.0])
    Qp = np.asarray(process_noise(jnp.asarray(B), jnp.asarray(u), s_w, jnp.asarray(R)))
    np.testing.assert_allclose(Qp, B @ np.diag((s_w * u) ** 2) @ B.T + Q_FLOOR * R, rtol=1e-12)
    assert np.min(np.linalg.eigvalsh(Qp)) > 0


def test_filter_converges_below_the_measurement_noise():
    """CW model of the rendezvous phase (30 s), no input, the thesis' measurement noise and an
    exact truth: P converges and the estimate's RMS error is well below the raw noise."""
    A, B = PARAMS.A[0], PARAMS.B[0]
    R = measurement_covariance(LAYOUT, D)
    Qp = process_noise(B, jnp.zeros(3), thrust_error_fraction(D, 30.0), R)
    sigma = jnp.sqrt(jnp.diag(R))
    steps = 400
    noise = jax.random.normal(jax.random.key(7), (steps, 6)) * sigma

    def body(carry, e):
        nav, x = carry
        nav = nav_update(nav, x + e, R)
        out = (nav.x_hat - x, e, nav.P)
        nav = nav_predict(nav, A, B, jnp.zeros(3), Qp)
        return (nav, A @ x), out

    x0 = jnp.asarray(X0)
    nav0 = nav_init(x0 + noise[0], R)
    _, (err, raw, Ps) = jax.lax.scan(
        body, (nav_predict(nav0, A, B, jnp.zeros(3), Qp), A @ x0), noise[1:]
    )
    err, raw, Ps = np.asarray(err), np.asarray(raw), np.asarray(Ps)
    # the covariance has converged: the last 50 steps change it by < 0.1 %
    np.testing.assert_allclose(Ps[-50], Ps[-1], rtol=1e-3, atol=1e-15)
    # steady state: the estimate's RMS error per axis is a fraction of the raw noise
    rms = np.sqrt(np.mean(err[100:] ** 2, axis=0))
    raw_rms = np.sqrt(np.mean(raw[100:] ** 2, axis=0))
    assert np.all(raw_rms > 0.9 * np.asarray(sigma))
    assert np.all(rms < 0.3 * raw_rms), rms / raw_rms
    # and the filter is not overconfident (the truth has no process noise)
    assert np.all(rms < 2.0 * np.sqrt(np.diag(Ps[-1])))


@pytest.mark.slow  # 18 s; `pytest -m slow`
def test_filtered_thesis_vbar_docks():
    """thesis-vbar flown disturbed with the filter through the batch engine over 8 keys: 8 of 8
    dock, within 136 steps (measured). Without the filter the same 8 runs dock once (measured;
    not flown here: a second engine program would double the compile time of this file)."""
    keys = jax.random.split(jax.random.key(0), 8)
    x0s = jnp.tile(jnp.asarray(X0), (8, 1))
    loop = VBAR.loop(disturbed=True, nav_filter=True)
    m = fly_batch(loop, PARAMS, x0s, keys, config=EngineConfig(slots=8, chunk=8))
    assert int(np.sum(m.docked)) >= 7, m.status
    assert np.all(np.asarray(m.status)[np.asarray(m.docked)] == RunStatus.DOCKED)


def test_nav_filter_needs_disturbed():
    with pytest.raises(ValueError, match="nav_filter"):
        VBAR.loop(nav_filter=True)
    with pytest.raises(ValueError, match="nav_filter"):
        LoopConfig(family_config=None, nav_filter=True)
    assert VBAR.loop(disturbed=True, nav_filter=True).config.nav_filter


@pytest.mark.parametrize("bad", [0.0, -60.0, float("nan"), "600", True])
def test_bad_time_limit(bad):
    with pytest.raises(ValueError, match="time_limit_s"):
        VBAR.loop(time_limit_s=bad)


def test_time_limit_ends_the_run():
    """A 90 s limit with 30 s rendezvous steps: the run ends TIMEOUT after the third step (its
    end time reaches the limit), then idles."""
    loop = VBAR.loop(n_steps=8, time_limit_s=90.0, N=(5, 5, 5))
    assert loop.config.time_limit_s == 90.0
    infos, m = jax.jit(lambda: fly(loop, PARAMS, X0))()
    assert int(m.status) == RunStatus.TIMEOUT and not bool(m.docked)
    assert int(m.steps) == 3
    np.testing.assert_array_equal(np.asarray(infos.active), [True] * 3 + [False] * 5)
    np.testing.assert_array_equal(np.asarray(infos.dt)[:3], [30.0] * 3)
    assert float(np.sum(infos.dt)) == 3 * 30.0 == float(np.sum(m.phase_time_s))
    assert float(infos.t[2]) < 90.0 <= float(infos.t[2] + infos.dt[2])
