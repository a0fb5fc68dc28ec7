"""Navigation noise, Gauss-Markov thrust error and minimum impulse bit (rvdjax.disturbances),
and the disturbed closed loops (a PRNG key per run)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from scipy.integrate import quad_vec

from rvdjax.disturbances import (
    disturbances,
    gm_discretize,
    gm_init,
    gm_step,
    measure,
    minimum_impulse_bit,
    thrust_factor,
)
from rvdjax.loop import fly
from rvdjax.scenarios import get_scenario
from rvdjax.solver import Status

D = disturbances()  # paper 003 Table 5.1
F = np.array([[-1.0 / 3600.0, 1.0], [-(2.6e-4**2), -2.0 * 2.6e-4]])
GGT = np.diag([3.0 / np.sqrt(600.0), 1.1267e-8]) ** 2


@pytest.mark.parametrize("dt", [1.0, 30.0, 600.0])
def test_gauss_markov_discretisation_is_exact(dt):
    """Phi = expm(F dt) and Q_d = int_0^dt e^{Fs} G G^T e^{F^T s} ds, by quadrature."""
    Phi, Qd = gm_discretize(D, dt)
    # entries span ~1e-5 to ~5e2 at dt = 600 s: an entry is judged against the matrix's norm
    # (a few ulps of it), not its own magnitude
    ref_phi = scipy.linalg.expm(F * dt)
    np.testing.assert_allclose(Phi, ref_phi, rtol=1e-12, atol=1e-13 * np.linalg.norm(ref_phi))
    ref = quad_vec(
        lambda s: scipy.linalg.expm(F * s) @ GGT @ scipy.linalg.expm(F * s).T,
        0.0,
        dt,
        epsabs=0.0,
        epsrel=1e-12,
    )[0]
    np.testing.assert_allclose(Qd, ref, rtol=1e-9, atol=1e-12 * np.linalg.norm(ref))


def test_gauss_markov_statistics():
    """Simulated w over many axes: its spread after 2 h matches the covariance propagated
    with the continuous Lyapunov equation from w(0) ~ N(0, 1) % (a few per cent, Fig. 5.1)."""
    n, dt, steps = 4000, 30.0, 240
    key = jax.random.key(0)
    state = gm_init(key, D, n)
    keys = jax.random.split(jax.random.key(1), steps)
    state = jax.lax.fori_loop(0, steps, lambda k, s: gm_step(keys[k], s, D, dt), state)
    P0 = np.diag([1.0, 0.0])
    T = steps * dt
    Phi = scipy.linalg.expm(F * T)
    # P(T) = Phi P0 Phi^T + (P_inf - Phi P_inf Phi^T), P_inf from F P + P F^T + G G^T = 0
    P_inf = scipy.linalg.solve_continuous_lyapunov(F, -GGT)
    P_T = Phi @ P0 @ Phi.T + P_inf - Phi @ P_inf @ Phi.T
    std = float(np.std(np.asarray(state[:, 0])))
    assert std == pytest.approx(np.sqrt(P_T[0, 0]), rel=0.05)
    assert 1.0 < np.sqrt(P_inf[0, 0]) < 7.0  # percent
    assert np.all(np.abs(np.asarray(thrust_factor(state)) - 1.0) < 0.5)


def test_measure_and_minimum_impulse_bit():
    d = disturbances(sigma_pos=0.05, sigma_vel=1e-3, sigma_att=0.01, thrust_max=0.5, mib_s=0.02)
    x = jnp.arange(6.0)
    xs = jax.vmap(lambda k: measure(k, x, d, (0, 1), (3, 4), att=(2,)))(
        jax.random.split(jax.random.key(2), 20000)
    )
    err = np.asarray(xs - x)
    np.testing.assert_allclose(
        err.std(axis=0), [0.05, 0.05, 0.01, 1e-3, 1e-3, 0.0], rtol=0.03, atol=1e-15
    )
    # pulses |J| / F_max: 0.004 / 0.5 = 8 ms < 20 ms is dropped; 0.02 / 0.5 = 40 ms is kept
    out = minimum_impulse_bit(jnp.array([0.004, -0.02, 0.0]), d)
    np.testing.assert_array_equal(np.asarray(out), [0.0, -0.02, 0.0])


@pytest.mark.parametrize(
    "kw, word",
    [
        (dict(sigma_pos=-0.1), "sigma_pos"),
        (dict(tau=0.0), "tau"),
        (dict(eta_w=float("nan")), "eta_w"),
        (dict(thrust_max=-1.0), "thrust_max"),
    ],
)
def test_bad_disturbances(kw, word):
    with pytest.raises(ValueError, match=word):
        disturbances(**kw)


@pytest.mark.slow  # 13 s; `pytest -m slow`
def test_disturbed_rotating_target_batch():
    """A batch of disturbed runs (one key each): every run ends with a valid status per step,
    nothing non-finite escapes, the same key reproduces a run and different keys differ."""
    sc = get_scenario("rotating-target-b")
    params, x0 = sc.build()
    loop = sc.loop("paper", disturbed=True)
    sp = sc.solver_params("paper")
    run = jax.jit(jax.vmap(lambda k: fly(loop, params, x0, k, sp)))
    keys = jax.random.split(jax.random.key(3), 4)
    infos, m = run(jnp.concatenate([keys, keys[:1]]))
    infos, m = jax.tree.map(np.asarray, (infos, m))
    for leaf in jax.tree.leaves(m):
        assert np.all(np.isfinite(leaf) | np.isinf(leaf))  # inf only as "never docked"
    assert np.all(np.isfinite(infos.x)) and np.all(np.isfinite(infos.u))
    st = infos.status[infos.active]
    assert np.all((st == Status.CONVERGED) | (st == Status.MAX_ITER))
    np.testing.assert_array_equal(infos.x[0], infos.x[-1])  # same key, same run
    assert not np.allclose(infos.x[0], infos.x[1])
    assert not np.allclose(infos.u[0], infos.u_cmd[0])  # the thrust error acts
    assert np.all(m.docked[:4])
    # undisturbed: the key is ignored
    calm = sc.loop("paper")
    a = jax.jit(lambda k: fly(calm, params, x0, k, sp)[1].effort_l1_N_s)
    assert float(a(keys[0])) == float(a(keys[1]))
