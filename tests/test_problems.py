"""Tests of rvdjax.problems: the fastmpc-3d first-step OCP (paper 000 Table 1)."""

import clarabel
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl
import scipy.sparse as sp

import rvdjax  # noqa: F401  (enables x64)
from rvdjax.constraints import sphere_keep_out
from rvdjax.problems import (
    FASTMPC3D,
    fastmpc3d_first_step,
    fastmpc3d_first_step_batch,
    perturbed_x0,
    stack_ocps,
)
from rvdjax.qp import qp_objective, split_solution, to_qp


def clarabel_solve(qp):
    """Solve a rvdjax.qp.QP with Clarabel (equalities first); return (status, x, z)."""
    n_eq, n_in = qp.A_eq.shape[0], qp.G.shape[0]
    A = sp.vstack([qp.A_eq, qp.G]).tocsc()
    b = np.concatenate([qp.b_eq, qp.h])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = 1e-10
    settings.tol_gap_rel = 1e-12
    settings.tol_feas = 1e-12
    cones = [clarabel.ZeroConeT(n_eq), clarabel.NonnegativeConeT(n_in)]
    sol = clarabel.DefaultSolver(sp.triu(qp.P).tocsc(), qp.q, A, b, cones, settings).solve()
    return str(sol.status), np.array(sol.x), np.array(sol.z)


@pytest.fixture(scope="module")
def ocp():
    return fastmpc3d_first_step()


@pytest.fixture(scope="module")
def hard_solution(ocp):
    qp = to_qp(ocp, soft=False)
    status, x, z = clarabel_solve(qp)
    return qp, status, x, z


def test_counts_and_shapes(ocp):
    assert (ocp.N, ocp.nx, ocp.nu, ocp.mu, ocp.mx) == (30, 6, 3, 6, 2)
    np.testing.assert_array_equal(ocp.x0, FASTMPC3D["x0"])
    np.testing.assert_array_equal(ocp.x_ref, 0.0)
    qp = to_qp(ocp, soft=False)
    assert qp.n_plan == 270 and qp.P.shape == (270, 270)
    assert qp.A_eq.shape == (180, 270)
    assert qp.G.shape == (240, 270)
    qp_soft = to_qp(ocp, soft=True)
    assert qp_soft.P.shape == (330, 330) and qp_soft.G.shape == (300, 330)
    free = to_qp(fastmpc3d_first_step(obstacles=False), soft=False)
    assert free.G.shape == (180, 270) and free.A_eq.shape == (180, 270)


def test_weights_and_terminal_dare(ocp):
    A, B = np.asarray(ocp.A[0]), np.asarray(ocp.B[0])
    Q, R = np.diag(FASTMPC3D["Q"]), np.diag(FASTMPC3D["R"])
    np.testing.assert_array_equal(ocp.Q[0], Q)
    np.testing.assert_array_equal(ocp.R[5], R)
    P_ref = sl.solve_discrete_are(A, B, Q, R)
    np.testing.assert_allclose(ocp.Q[-1], P_ref, rtol=1e-9, atol=1e-9 * np.max(P_ref))
    np.testing.assert_array_equal(ocp.fu, 20.0)


def _centres(t_s):
    """Obstacle centres (len(t_s), 2, 3) of Table 1 at the given times (straight lines)."""
    o = np.asarray(FASTMPC3D["obstacles"])
    return o[None, :, :3] + np.asarray(t_s)[:, None, None] * o[None, :, 3:]


def test_keepout_rows_match_eq8_geometry():
    """Rows of paper 000 Eq. 8 with a unit normal: F r - f = R (1 - eq8) / 2 (in metres)."""
    rng = np.random.default_rng(0)
    N, n_obs = 4, 2
    p = rng.normal(size=(N, 3)) * 100
    o = rng.normal(size=(N, n_obs, 3)) * 100
    radii = np.array([20.0, 50.0])
    block = sphere_keep_out(p, o, radii, 6)
    Fx, fx = np.asarray(block.F), np.asarray(block.f)
    assert Fx.shape == (N, n_obs, 6) and fx.shape == (N, n_obs)
    assert np.all(Fx[..., 3:] == 0)
    np.testing.assert_allclose(np.linalg.norm(Fx, axis=-1), 1.0, rtol=1e-14)
    for t in range(N):
        for j in range(n_obs):
            S = np.eye(3) / radii[j] ** 2
            d = p[t] - o[t, j]
            r0 = o[t, j] + d / np.sqrt(d @ S @ d)
            # Eq. 8: 1 <= 2 (r0-o)^T S (r-o) - (r0-o)^T S (r0-o)
            for r in rng.normal(size=(20, 3)) * 150 + o[t, j]:
                eq8 = 2 * (r0 - o[t, j]) @ S @ (r - o[t, j]) - (r0 - o[t, j]) @ S @ (r0 - o[t, j])
                lhs = Fx[t, j, :3] @ r - fx[t, j]  # <= 0 means feasible
                assert lhs == pytest.approx(radii[j] * (1 - eq8) / 2, abs=1e-9)
            # r0 lies on the boundary of the half-space; the whole ball is on the wrong side
            assert Fx[t, j, :3] @ r0 == pytest.approx(fx[t, j], abs=1e-9)
            u = rng.normal(size=(50, 3))
            sphere = o[t, j] + radii[j] * u / np.linalg.norm(u, axis=1, keepdims=True)
            assert np.all(sphere @ Fx[t, j, :3] >= fx[t, j] - 1e-9)
    # jittable
    bj = jax.jit(lambda p, o, r: sphere_keep_out(p, o, r, 6))(p, o, radii)
    np.testing.assert_allclose(bj.F, Fx, rtol=1e-14, atol=1e-14 * np.linalg.norm(Fx))
    np.testing.assert_allclose(bj.f, fx, rtol=1e-14, atol=1e-14 * np.linalg.norm(fx))


def test_drift_guess_and_obstacle_motion(ocp):
    """The first step's keep-out rows are linearised about the unforced drift of x0, at the
    obstacles' positions at the stage instants (t + 1) Ts."""
    x = np.asarray(FASTMPC3D["x0"])
    A = np.asarray(ocp.A[0])
    drift = []
    for _ in range(ocp.N):
        x = A @ x
        drift.append(x[:3])
    ref = sphere_keep_out(np.asarray(drift), _centres(15.0 * np.arange(1, 31)), (20.0, 50.0), 6)
    np.testing.assert_allclose(ocp.Fx, ref.F, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(ocp.fx, ref.f, rtol=1e-10)


def test_hard_qp_solved_and_keepout_respected(ocp, hard_solution):
    qp, status, x, z = hard_solution
    assert status == "Solved"
    u, xs = split_solution(x, ocp.N, ocp.nx, ocp.nu)
    assert np.max(np.abs(u)) <= 20.0 + 1e-6
    assert np.max(np.abs(u)) > 19.0  # the thrust limit is active on the first step
    # the linearised rows are conservative: the true spheres are avoided too
    centres = _centres(15.0 * np.arange(1, 31))
    dist = np.linalg.norm(xs[:, None, :3] - centres, axis=-1)
    assert np.all(dist >= np.asarray(FASTMPC3D["radii"]) - 1e-6)
    # some keep-out row is active (the obstacle matters), with a multiplier well below rho
    # (rows in metres: multipliers per metre of penetration)
    lam_obs = z[qp.A_eq.shape[0] :].reshape(30, 8)[:, 6:]
    assert np.max(lam_obs) > 1e2
    assert np.max(lam_obs) < 1e-1 * float(np.min(ocp.rho))


@pytest.mark.parametrize("perturbed", [False, True])
def test_soft_optimum_equals_hard(ocp, hard_solution, perturbed):
    if perturbed:
        ocp = fastmpc3d_first_step(np.asarray(perturbed_x0(7, 1))[0])
        hard = to_qp(ocp, soft=False)
        status, x, _ = clarabel_solve(hard)
        assert status == "Solved"
    else:
        hard, status, x, _ = hard_solution
    f_hard = qp_objective(hard, x)
    soft = to_qp(ocp, soft=True)
    status_s, xs, _ = clarabel_solve(soft)
    assert status_s == "Solved"
    f_soft = qp_objective(soft, xs)
    assert f_soft == pytest.approx(f_hard, rel=1e-8)
    assert np.max(xs[soft.n_plan :]) < 1e-6  # slacks are zero: no keep-out violated


def test_perturbed_x0():
    a = np.asarray(perturbed_x0(1, 64))
    b = np.asarray(perturbed_x0(jax.random.PRNGKey(1), 64))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (64, 6)
    d = a - np.asarray(FASTMPC3D["x0"])
    assert np.all(np.abs(d[:, :3]) <= 20.0) and np.all(np.abs(d[:, 3:]) <= 0.05)
    assert np.std(d[:, 0]) > 5.0
    c = np.asarray(perturbed_x0(2, 3, scale_pos=1.0, scale_vel=0.0))
    assert np.all(np.abs(c - np.asarray(FASTMPC3D["x0"]))[:, :3] <= 1.0)
    np.testing.assert_array_equal(c[:, 3:], 0.0)


def test_batch_matches_individual_builds():
    x0s = perturbed_x0(5, 3)
    batched = fastmpc3d_first_step_batch(x0s)
    ref = stack_ocps([fastmpc3d_first_step(np.asarray(x)) for x in x0s])
    assert batched.B.shape == (3, 30, 6, 3)
    for name, a, b in zip(batched._fields, batched, ref, strict=True):
        assert a.shape == b.shape, name
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12, err_msg=name)
    free = fastmpc3d_first_step_batch(x0s, obstacles=False)
    assert free.Fx.shape == (3, 30, 2, 6) and float(jnp.sum(free.x_mask)) == 0.0
    with pytest.raises(ValueError, match="x0s"):
        fastmpc3d_first_step_batch(jnp.zeros((3, 4)))
