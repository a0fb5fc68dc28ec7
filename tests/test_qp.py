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
