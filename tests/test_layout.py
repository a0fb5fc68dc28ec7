"""The batch-last layout of a primal-dual iteration: the same products and reductions as one
problem at a time, and whole solves that agree with the vmapped solver and with Clarabel."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ocp_factory import SHAPE_CLASSES, random_ocp

from rvdjax.problems import stack_ocps
from rvdjax.qp import to_qp
from rvdjax.solver import SolverParams, SolverSettings, Status, finish, iterate, solve, start
from rvdjax.solver.barrier import objective
from rvdjax.solver.driver import finished
from rvdjax.solver.layout import BATCH_LAST, ONE, shared_to_last, to_first, to_last

ACCURATE = SolverSettings()
PARAMS = SolverParams()


def test_products_and_reductions_match_one_problem_at_a_time():
    """Every product and reduction of BATCH_LAST, on a batch moved last (and on an operand
    shared by the batch, with a trailing axis of size 1), equals ONE's on each problem."""
    rng = np.random.default_rng(0)
    b, t, i, j = 5, 4, 3, 6
    F = jnp.asarray(rng.standard_normal((b, t, i, j))).at[1, 2, 0, 3].set(-20.0)
    v = jnp.asarray(rng.standard_normal((b, t, j)))
    w = jnp.asarray(rng.standard_normal((b, t, i)))
    shared = jnp.asarray(rng.standard_normal((t, i, j)))
    ref = {
        "mv": jax.vmap(ONE.mv)(F, v),
        "mtv": jax.vmap(ONE.mtv)(F, w),
        "gram": jax.vmap(ONE.gram)(F, w),
        "shared_mv": jax.vmap(ONE.mv, in_axes=(None, 0))(shared, v),
        "total": jax.vmap(ONE.total)(F),
        "largest": jax.vmap(ONE.largest)(F),
        "smallest": jax.vmap(ONE.smallest)(F),
        "every": jax.vmap(ONE.every)(F > -10.0),
    }
    Fl, vl, wl = to_last((F, v, w))
    got = {
        "mv": BATCH_LAST.mv(Fl, vl),
        "mtv": BATCH_LAST.mtv(Fl, wl),
        "gram": BATCH_LAST.gram(Fl, wl),
        "shared_mv": BATCH_LAST.mv(shared_to_last(shared), vl),
        "total": BATCH_LAST.total(Fl),
        "largest": BATCH_LAST.largest(Fl),
        "smallest": BATCH_LAST.smallest(Fl),
        "every": BATCH_LAST.every(Fl > -10.0),
    }
    for name, a in ref.items():
        np.testing.assert_allclose(to_first(got[name]), a, rtol=1e-13, atol=1e-13, err_msg=name)
    np.testing.assert_array_equal(ref["every"], [True, False, True, True, True])


@jax.jit
def _solve_batch_last(ocps):
    """Start each problem, iterate the whole batch in the batch-last layout until every
    problem has finished, finish each problem."""
    ocps, states = jax.vmap(lambda o: start(o, ACCURATE, PARAMS))(ocps)
    ob, sb = to_last(ocps), to_last(states)
    sb = jax.lax.while_loop(
        lambda s: ~jnp.all(finished(s, ACCURATE)),
        lambda s: iterate(ob, s, ACCURATE, PARAMS, BATCH_LAST),
        sb,
    )
    sols = jax.vmap(lambda o, s: finish(o, s, ACCURATE, PARAMS))(ocps, to_first(sb))
    return sols._replace(objective=jax.vmap(objective)(ocps, sols.u, sols.x))


def test_batch_last_solves_match_vmap_and_clarabel(clarabel_solve):
    """Twelve random feasible OCPs (mixed active rows): the batch-last iterations take the
    same iterations as the vmapped solver, agree with its solutions to rounding, and reach
    Clarabel's optimum."""
    ocps = [random_ocp(seed, SHAPE_CLASSES["medium"]) for seed in range(12)]
    batch = stack_ocps(ocps)
    last = _solve_batch_last(batch)
    ref = jax.jit(jax.vmap(lambda o: solve(o, ACCURATE, params=PARAMS)))(batch)
    np.testing.assert_array_equal(last.status, ref.status)
    np.testing.assert_array_equal(last.iterations, ref.iterations)
    assert np.all(np.asarray(last.status) == Status.CONVERGED)
    scale = float(np.max(np.abs(ref.u)))
    np.testing.assert_allclose(last.u, ref.u, rtol=0, atol=1e-8 * scale)
    for k, ocp in enumerate(ocps):
        _, J, status = clarabel_solve(to_qp(ocp, soft=False))
        assert status == "Solved"
        assert abs(float(last.objective[k]) - J) <= 1e-6 * (1.0 + abs(J)), k


def test_batch_last_needs_the_accurate_riccati_solver():
    ocp = random_ocp(0, SHAPE_CLASSES["small"])
    paper = SolverSettings.paper()
    o, st = start(ocp, paper, PARAMS)
    with pytest.raises(ValueError, match="mode='accurate'"):
        iterate(o, st, paper, PARAMS, BATCH_LAST)
