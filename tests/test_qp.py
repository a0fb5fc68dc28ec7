"""rvdjax.qp.to_qp against the OCP's equations, evaluated stage by stage with plain loops
(an independent reading of the standard form in the module docstring), on random problems
with some rows masked off, in the soft and the hard form."""

from __future__ import annotations

import numpy as np
import pytest
from ocp_factory import SHAPE_CLASSES, random_ocp

import rvdjax  # noqa: F401  (enables x64)
from rvdjax.qp import split_solution, to_qp


def _active(mask_row):
    return [k for k, w in enumerate(mask_row) if w > 0]


@pytest.mark.parametrize("soft", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_to_qp_evaluates_the_ocp(seed, soft):
    o = random_ocp(seed, SHAPE_CLASSES["medium"])
    rng = np.random.default_rng(100 + seed)
    # mask off further rows at random, so stages differ in their active rows
    o = o._replace(
        u_mask=np.asarray(o.u_mask) * (rng.random(o.u_mask.shape) > 0.3),
        x_mask=np.asarray(o.x_mask) * (rng.random(o.x_mask.shape) > 0.4),
    )
    o = type(o)(*(np.asarray(a, dtype=float) for a in o))
    N, nx, nu = o.B.shape
    qp = to_qp(o, soft=soft)
    x_rows = [_active(o.x_mask[t]) for t in range(N)]
    n_slack = sum(map(len, x_rows)) if soft else 0
    assert qp.n_plan == N * (nx + nu) and qp.P.shape == (qp.n_plan + n_slack,) * 2

    z = rng.normal(size=qp.n_plan + n_slack)
    u, x = split_solution(z, N, nx, nu)
    s = z[qp.n_plan :]

    cost = 0.0
    for t in range(N):
        e = x[t] - o.x_ref[t]
        cost += e @ o.Q[t] @ e + u[t] @ o.R[t] @ u[t] + o.q[t] @ x[t] + o.r[t] @ u[t]
    if soft:
        cost += sum(
            o.rho[t, k] * s_i
            for s_i, (t, k) in zip(s, [(t, k) for t in range(N) for k in x_rows[t]], strict=True)
        )
    zPz = z @ (qp.P @ z)
    assert 0.5 * zPz + qp.q @ z + qp.const == pytest.approx(cost, rel=1e-12, abs=1e-9)
    # symmetric as far as the random Q_t, R_t are (to rounding)
    assert abs(qp.P - qp.P.T).max() <= 1e-12 * abs(qp.P).max()

    prev = o.x0
    dyn = []
    for t in range(N):
        dyn.append(x[t] - o.A[t] @ prev - o.B[t] @ u[t] - o.c[t])
        prev = x[t]
    np.testing.assert_allclose(qp.A_eq @ z - qp.b_eq, np.concatenate(dyn), atol=1e-10)

    rows, j = [], 0
    for t in range(N):
        rows += [o.Fu[t, k] @ u[t] - o.fu[t, k] for k in _active(o.u_mask[t])]
        if soft:
            xs = [o.Fx[t, k] @ x[t] - s[j + i] - o.fx[t, k] for i, k in enumerate(x_rows[t])]
            rows += xs + [-s[j + i] for i in range(len(x_rows[t]))]
            j += len(x_rows[t])
        else:
            rows += [o.Fx[t, k] @ x[t] - o.fx[t, k] for k in x_rows[t]]
    np.testing.assert_allclose(qp.G @ z - qp.h, np.asarray(rows), atol=1e-10)


def _condensed_as_qp(c):
    """The condensed problem in the standard form (bounds as rows, no equalities)."""
    import scipy.sparse as sp

    from rvdjax.qp import QP

    nw = c.H.shape[0]
    eye = np.eye(nw)
    up, lo = np.isfinite(c.ub), np.isfinite(c.lb)
    G = np.vstack([c.G, eye[up], -eye[lo]])
    h = np.concatenate([c.h, c.ub[up], -c.lb[lo]])
    return QP(
        sp.csc_matrix(c.H), c.f, sp.csc_matrix((0, nw)), np.zeros(0), sp.csc_matrix(G), h,
        c.const, nw,
    )  # fmt: skip


@pytest.mark.parametrize("soft", [True, False])
@pytest.mark.parametrize("seed", [0, 1])
def test_condense_same_problem(seed, soft):
    """The condensed QP (states eliminated) is the same problem: its points map to points that
    satisfy the dynamics with the same objective, and its optimum (Clarabel) is the sparse
    form's optimum (Clarabel)."""
    from rvdjax import peers
    from rvdjax.qp import condense, qp_objective

    o = random_ocp(seed, SHAPE_CLASSES["medium"])
    o = type(o)(*(np.asarray(a, dtype=float) for a in o))
    N, nx, nu = o.B.shape
    qp = to_qp(o, soft=soft)
    c = condense(qp)
    n_slack = qp.P.shape[0] - qp.n_plan
    assert c.H.shape == (N * nu + n_slack,) * 2
    # thrust boxes and s >= 0 became bounds: every input has both, every slack a lower one
    assert np.all(np.isfinite(c.lb[: N * nu])) and np.all(np.isfinite(c.ub[: N * nu]))
    assert np.all(c.lb[N * nu :] == 0.0)

    rng = np.random.default_rng(seed)
    w = rng.normal(size=c.H.shape[0])
    z = c.Z @ w + c.z0
    np.testing.assert_allclose(qp.A_eq @ z, qp.b_eq, atol=1e-9 * (1 + np.abs(qp.b_eq).max()))
    J_w = 0.5 * w @ c.H @ w + c.f @ w + c.const
    assert J_w == pytest.approx(qp_objective(qp, z), rel=1e-10)

    ref = peers.solve_clarabel(qp)
    res = peers.solve_clarabel(_condensed_as_qp(c))
    assert ref.status == res.status == "Solved"
    z_c = c.Z @ res.z + c.z0
    assert qp_objective(qp, z_c) == pytest.approx(ref.objective, rel=1e-8, abs=1e-8)
    np.testing.assert_allclose(z_c[: qp.n_plan], ref.z[: qp.n_plan], atol=1e-5)


def test_condense_needs_to_qp_shapes():
    from rvdjax.qp import condense

    qp = to_qp(random_ocp(0, SHAPE_CLASSES["small"]))
    with pytest.raises(ValueError, match="to_qp"):
        condense(qp._replace(nu=0))
