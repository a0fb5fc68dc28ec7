"""A back-solve the implicit derivative cannot use is zeroed and counted, never silent: the
cotangent of ``SolverParams.derivative_probe`` counts the solves zeroed behind a gradient."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from ocp_factory import ShapeClass, random_ocp

from rvdjax.solver import SolverParams, SolverSettings, Status, solve

SETTINGS = SolverSettings()
SHAPE = ShapeClass(nx=2, nu=1, N=5, n_fu=1, mx=2)


def _probe_grad(ocps):
    """d/d(x0, probe) of the sum over the batch of sum(u) (one probe per solve)."""

    def loss(x0s, probes):
        def one(x0, probe, ocp):
            sol = solve(ocp._replace(x0=x0), SETTINGS, params=SolverParams(derivative_probe=probe))
            return jnp.sum(sol.u), sol.status

        u, status = jax.vmap(one)(x0s, probes, ocps)
        return jnp.sum(u), status

    x0s = ocps.x0
    (_, status), (g_x0, g_probe) = jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))(
        x0s, jnp.zeros(x0s.shape[0])
    )
    return np.asarray(status), np.asarray(g_x0), np.asarray(g_probe)


def test_zeroed_back_solves_are_counted():
    ocps = [random_ocp(s, SHAPE) for s in range(3)]
    bad = ocps[1]._replace(x0=jnp.full_like(ocps[1].x0, jnp.nan))  # a non-finite solve
    batch = jax.tree.map(lambda *a: jnp.stack(a), ocps[0], bad, ocps[2])
    status, g_x0, g_probe = _probe_grad(batch)
    assert status[1] == Status.NONFINITE and status[0] != Status.NONFINITE
    np.testing.assert_array_equal(g_probe, [0.0, 1.0, 0.0])
    assert np.all(np.isfinite(g_x0)) and np.all(g_x0[1] == 0.0)
    assert np.any(g_x0[0] != 0.0)
