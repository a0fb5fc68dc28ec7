"""Paper 001's dual solver (rvdjax.solver.dual, PQP of its ref. 38): run long enough it reaches
Clarabel's optimum of the soft QP; capped at 100 iterations it returns a flyable plan; bad data
gives a status, never a NaN."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from ocp_factory import SHAPE_CLASSES, random_ocp

import rvdjax  # noqa: F401  (float64)
from rvdjax.qp import split_solution, to_qp
from rvdjax.solver import SolverParams, SolverSettings, Status, solve, start
from rvdjax.solver.dual import condense

LONG = SolverSettings(mode="dual", max_iter=20000)
PAPER001 = SolverSettings(mode="dual", max_iter=100)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dual_method_reaches_clarabel(seed, clarabel_solve):
    ocp = random_ocp(seed, SHAPE_CLASSES["medium"])
    z, J, status = clarabel_solve(to_qp(ocp, soft=True))
    assert status == "Solved"
    u_ref, x_ref = split_solution(z, ocp.N, ocp.nx, ocp.nu)
    sol = solve(ocp, LONG, params=SolverParams(tol=1e-7))
    assert int(sol.status) in (Status.CONVERGED, Status.INFEASIBLE)
    scale = float(np.max(np.abs(u_ref))) + 1.0
    np.testing.assert_allclose(np.asarray(sol.u), u_ref, atol=1e-4 * scale)
    np.testing.assert_allclose(np.asarray(sol.x), x_ref, atol=1e-4 * (np.abs(x_ref).max() + 1))
    assert float(sol.objective) == pytest.approx(J, rel=1e-6, abs=1e-8)


def test_condensed_qp_is_the_ocp():
    """The condensed cost and rows evaluated at a plan equal the OCP's own at its states."""
    ocp = random_ocp(3, SHAPE_CLASSES["small"], time_varying=True)
    P, f, G, g, soft, rho, Gam, x_free = (np.asarray(a) for a in condense(ocp))
    U = np.random.default_rng(0).normal(size=ocp.N * ocp.nu)
    x = x_free + np.einsum("tia,a->ti", Gam, U)
    u = U.reshape(ocp.N, ocp.nu)
    # states by the recursion
    xs, xt = [], np.asarray(ocp.x0)
    for t in range(ocp.N):
        xt = np.asarray(ocp.A[t]) @ xt + np.asarray(ocp.B[t]) @ u[t] + np.asarray(ocp.c[t])
        xs.append(xt)
    np.testing.assert_allclose(x, np.array(xs), atol=1e-10)

    # cost up to its constant: differences between two plans
    def cost(u, x):
        e = x - np.asarray(ocp.x_ref)
        return sum(
            e[t] @ np.asarray(ocp.Q[t]) @ e[t] + u[t] @ np.asarray(ocp.R[t]) @ u[t]
            + np.asarray(ocp.q[t]) @ x[t] + np.asarray(ocp.r[t]) @ u[t]
            for t in range(ocp.N)
        )  # fmt: skip

    U2 = U * 0.5
    x2 = x_free + np.einsum("tia,a->ti", Gam, U2)
    quad = lambda v: 0.5 * v @ P @ v + f @ v  # noqa: E731
    assert quad(U) - quad(U2) == pytest.approx(cost(u, x) - cost(U2.reshape(u.shape), x2))
    # rows: input rows then state rows (masked rows: zero with g = 1)
    on_u = np.asarray(ocp.u_mask) > 0
    on_x = np.asarray(ocp.x_mask) > 0
    gu = np.einsum("tmi,ti->tm", np.asarray(ocp.Fu), u) - np.asarray(ocp.fu)
    gx = np.einsum("tmi,ti->tm", np.asarray(ocp.Fx), x) - np.asarray(ocp.fx)
    ours = G @ U - g
    n_u = gu.size
    np.testing.assert_allclose(ours[:n_u][on_u.ravel()], gu[on_u], atol=1e-10)
    np.testing.assert_allclose(ours[n_u:][on_x.ravel()], gx[on_x], atol=1e-10)
    assert np.all(soft[n_u:] == on_x.ravel()) and np.all(soft[:n_u] == 0)


def test_capped_dual_flies_and_reports():
    """100 iterations (paper 001): a finite plan whose states obey the dynamics, inputs within
    their hard rows up to the unconverged dual's error, a MAX_ITER or CONVERGED status; vmap
    equals single solves; the batch engine's start refuses the mode."""
    ocps = [random_ocp(s, SHAPE_CLASSES["medium"]) for s in range(4)]
    sols = [solve(o, PAPER001) for o in ocps]
    for o, s in zip(ocps, sols, strict=True):
        assert int(s.status) in (Status.MAX_ITER, Status.CONVERGED)
        assert int(s.iterations) == 100
        assert np.all(np.isfinite(np.asarray(s.u))) and np.isfinite(float(s.objective))
        xt = np.asarray(o.x0)
        for t in range(o.N):
            xt = np.asarray(o.A[t]) @ xt + np.asarray(o.B[t]) @ np.asarray(s.u[t]) + o.c[t]
            np.testing.assert_allclose(np.asarray(s.x[t]), xt, atol=1e-9)
    from rvdjax.problems import stack_ocps

    batch = jax.vmap(lambda o: solve(o, PAPER001))(stack_ocps(ocps))
    np.testing.assert_allclose(
        np.asarray(batch.u), np.stack([np.asarray(s.u) for s in sols]), atol=1e-12
    )
    with pytest.raises(ValueError, match="dual"):
        start(ocps[0], PAPER001, SolverParams())


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_dual_nonfinite_data(bad):
    ocp = random_ocp(0, SHAPE_CLASSES["small"])
    ocp = ocp._replace(x0=ocp.x0.at[0].set(bad))
    sol = solve(ocp, PAPER001)
    assert int(sol.status) == Status.NONFINITE
    assert np.all(np.asarray(sol.u) == 0.0)
