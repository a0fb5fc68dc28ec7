"""Reverse-mode derivatives of ``solve`` (the implicit custom VJP) against finite differences.

The solves use a fixed barrier weight (paper mode, kappa = 0.5, iterated to a 1e-13 residual),
so the solution map theta -> (u, x) is the smooth map of the barrier problem and the implicit
derivative is exact up to the solve's accuracy. Each check compares <grad, d> with a central
difference along a random direction d, Richardson-extrapolated (error O(h^4)), to a relative
1e-6, plus 1e-7 of |grad| |d| (directions nearly orthogonal to the gradient) and the
difference quotient's noise floor 1e-13 |loss| / h (the solves' accuracy).

The test problems have rows that matter at the solution: input slacks ~0.04 (barrier
curvature kappa / s^2 ~ 300, far above 2R) and, in the ``soft-violated`` cases, soft state
rows violated at the optimum (small rho; the solver then reports "infeasible", the exact-penalty
branch of the soft barrier is what is being differentiated).

All checks share a handful of module-level jitted functions, so the file compiles few times.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ocp_factory import ShapeClass, random_ocp

from rvdjax.dynamics import dare, discretize_zoh, planar2dof_continuous
from rvdjax.ocp import OCP, make_ocp
from rvdjax.solver import SolverParams, SolverSettings, Status, solve

SETTINGS = SolverSettings(mode="paper", max_iter=200)
DENSE = SolverSettings(mode="paper", max_iter=200, method="dense")
PARAMS = SolverParams(kappa=0.5, tol=1e-13)  # a fixed kappa, solved to convergence
SHAPE = ShapeClass(nx=4, nu=2, N=10, n_fu=2, mx=3)

_rng = np.random.default_rng(1234)
W_U = jnp.asarray(_rng.normal(size=(SHAPE.N, SHAPE.nu)))
W_X = jnp.asarray(_rng.normal(size=(SHAPE.N, SHAPE.nx)))

RTOL = 1e-6
ATOL_REL = 1e-7  # of |grad| |d|

# name -> (seed, rho): rho None is the factory's 1e4 (rows satisfied, barrier active); a small
# rho leaves soft rows violated at the optimum.
CASES = {
    "rows-active": (4, None),
    "rows-active-2": (9, None),
    "soft-violated": (4, 3.0),
    "soft-violated-2": (1, 1.0),
}
FIELDS = ("x0", "Q", "R", "x_ref", "q", "r", "c", "fx", "fu", "A", "B", "Fx", "Fu", "rho")


def _loss_with(settings):
    def loss(ocp: OCP):
        sol = solve(ocp, settings, params=PARAMS)
        return jnp.sum(W_U * sol.u) + jnp.sum(W_X * sol.x) + 1e-2 * sol.objective, sol

    return loss


_loss_and_sol = _loss_with(SETTINGS)


def _loss(ocp: OCP):
    return _loss_and_sol(ocp)[0]


LOSS_AND_SOL = jax.jit(_loss_and_sol)  # also serves as the plain solve of the tests


def _loss_value(ocp: OCP) -> float:
    return float(LOSS_AND_SOL(ocp)[0])


def _solve_fixed(ocp: OCP):
    return LOSS_AND_SOL(ocp)[1]


GRAD = jax.jit(jax.grad(_loss))
GRAD_DENSE = jax.jit(jax.grad(lambda o: _loss_with(DENSE)(o)[0]))


def _scaled(ocp: OCP, log_scales):
    """The OCP with Q and R multiplied by exp(log_scales[0]) and exp(log_scales[1])."""
    return ocp._replace(Q=ocp.Q * jnp.exp(log_scales[0]), R=ocp.R * jnp.exp(log_scales[1]))


GRAD_SCALED = jax.jit(jax.grad(lambda o, w: _loss(_scaled(o, w)), argnums=1))


def _fd(f, h):
    """Central difference of the scalar function f(t) at 0, Richardson-extrapolated.

    Returns (derivative estimate, its noise floor): the solves are accurate to ~1e-13
    relative, so differences of f are resolved to ~1e-13 |f| / h.
    """
    d1 = (f(h) - f(-h)) / (2 * h)
    d2 = (f(h / 2) - f(-h / 2)) / h
    return (4 * d2 - d1) / 3, 1e-13 * (1.0 + abs(f(0.0))) / h


def _assert_directional(gd, fd, g_norm_d_norm, what):
    fd, noise = fd
    err = abs(fd - gd)
    assert err <= RTOL * abs(gd) + ATOL_REL * g_norm_d_norm + noise, (
        f"{what}: grad.d = {gd:.12e}, finite difference {fd:.12e}, error {err:.2e}"
    )


def _case(name) -> OCP:
    seed, rho = CASES[name]
    return random_ocp(seed, SHAPE, rho=rho)


@pytest.fixture(scope="module", params=list(CASES))
def case(request):
    """(name, ocp, solution, gradient) of one test problem."""
    ocp = _case(request.param)
    sol = _solve_fixed(ocp)
    return request.param, ocp, sol, GRAD(ocp)


def test_cases_are_converged_with_active_rows(case):
    name, ocp, sol, _ = case
    status = int(sol.status)
    if name.startswith("soft-violated"):
        # Converged; "infeasible" only flags the violated soft rows.
        assert status in (Status.CONVERGED, Status.INFEASIBLE), Status.name(status)
        g = np.einsum("tij,tj->ti", np.asarray(ocp.Fx), np.asarray(sol.x)) - np.asarray(ocp.fx)
        assert np.max(np.where(np.asarray(ocp.x_mask) > 0, g, -np.inf)) > 1e-2
    else:
        assert status == Status.CONVERGED, Status.name(status)
        # The barrier terms matter: some input row's curvature kappa / s^2 dominates 2 R.
        su = np.asarray(ocp.fu) - np.einsum("tij,tj->ti", np.asarray(ocp.Fu), np.asarray(sol.u))
        su_min = np.min(su[np.asarray(ocp.u_mask) > 0])
        r_max = np.max(np.linalg.eigvalsh(np.asarray(ocp.R)))
        assert PARAMS.kappa / su_min**2 > 10 * 2 * r_max
    assert float(sol.residual) < 1e-12


@pytest.mark.parametrize("field", FIELDS)
def test_grad_matches_finite_differences(case, field):
    name, ocp, _, grad = case
    rng = np.random.default_rng([list(CASES).index(name), FIELDS.index(field)])
    a = np.asarray(getattr(ocp, field))
    d = rng.normal(size=a.shape)
    if field in ("Q", "R"):  # the weights are symmetric: perturb them symmetrically
        d = d + np.swapaxes(d, -1, -2)
    g = np.asarray(getattr(grad, field))
    assert np.all(np.isfinite(g))
    h = 1e-3 * max(np.max(np.abs(a)), 1.0) / np.max(np.abs(d))

    def f(t):
        return _loss_value(ocp._replace(**{field: jnp.asarray(a + t * d)}))

    gd = float(np.sum(g * d))
    _assert_directional(gd, _fd(f, h), np.linalg.norm(g) * np.linalg.norm(d), f"{name}/{field}")


@pytest.mark.parametrize(
    "field, index",
    [("x0", (2,)), ("A", (3, 0, 1)), ("A", (7, 2, 3)), ("B", (0, 1, 0)), ("B", (9, 3, 1))],
)
def test_grad_single_entries(field, index):
    """Entry-wise: one element of x0, A_t and B_t at a time (first and last stages)."""
    ocp = _case("rows-active")
    grad = GRAD(ocp)
    a = np.asarray(getattr(ocp, field))
    g = float(np.asarray(getattr(grad, field))[index])

    def f(t):
        b = a.copy()
        b[index] += t
        return _loss_value(ocp._replace(**{field: jnp.asarray(b)}))

    g_all = np.linalg.norm(np.asarray(getattr(grad, field)))
    _assert_directional(g, _fd(f, 1e-4), g_all, f"{field}{index}")


def test_grad_weight_scales(case):
    """d loss / d log(scale) of Q and of R, the tuning knobs of an MPC designer."""
    name, ocp, _, _ = case
    w0 = jnp.zeros(2)
    g = np.asarray(GRAD_SCALED(ocp, w0))
    for i, what in enumerate(("Q scale", "R scale")):
        e = np.eye(2)[i]

        def f(t, e=e):
            return _loss_value(_scaled(ocp, w0 + t * e))

        _assert_directional(g[i], _fd(f, 1e-3), np.linalg.norm(g), f"{name}/{what}")


def test_vmap_grad_equals_per_problem():
    ocps = [_case(n) for n in CASES]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *ocps)
    gb = jax.jit(jax.vmap(jax.grad(_loss)))(batch)
    for i, ocp in enumerate(ocps):
        gi = GRAD(ocp)
        for field in OCP._fields:
            np.testing.assert_allclose(
                np.asarray(getattr(gb, field))[i],
                np.asarray(getattr(gi, field)),
                rtol=1e-9,
                atol=1e-12 * (1 + np.max(np.abs(np.asarray(getattr(gi, field))))),
                err_msg=f"problem {i}, field {field}",
            )


def test_dense_method_same_gradient(case):
    name, ocp, _, grad = case
    gd = GRAD_DENSE(ocp)
    for field in OCP._fields:
        g_r = np.asarray(getattr(grad, field))
        np.testing.assert_allclose(
            np.asarray(getattr(gd, field)),
            g_r,
            rtol=1e-7,
            atol=1e-9 * (1 + np.max(np.abs(g_r))),
            err_msg=f"{name}/{field}",
        )


def test_nonfinite_x0_gives_finite_zero_implicit_gradient():
    ocp = _case("rows-active")
    bad = OCP(*(ocp._replace(x0=ocp.x0.at[1].set(jnp.nan))))
    sol = _solve_fixed(bad)
    assert int(sol.status) == Status.NONFINITE
    grad = GRAD(bad)
    for field in OCP._fields:
        assert np.all(np.isfinite(np.asarray(getattr(grad, field)))), field
    # Only the objective's explicit dependence (on the weights and rows, at the zero plan) is
    # left; every field that enters through the solution alone gets a zero gradient.
    for field in ("x0", "A", "B", "c", "Fu", "fu"):
        assert np.all(np.asarray(getattr(grad, field)) == 0.0), field


# --------------------------------------------------------------------------------------------
# Composition: sampling time -> ZOH discretisation -> DARE terminal weight -> solve
#
# A planar double integrator with the shapes of SHAPE (nx = 4, nu = 2, N = 10, 6 input rows,
# 3 state rows), so the forward solves reuse the compiled LOSS_AND_SOL.

_Q2 = np.diag([1.0, 1.0, 10.0, 10.0])
_R2 = np.diag([50.0, 50.0])
_MASS = 2.0
_TS = 2.0


def _make_planar_base() -> OCP:
    Ac, Bc = planar2dof_continuous(_MASS)
    Ad, Bd = discretize_zoh(Ac, Bc, _TS)
    return make_ocp(
        np.asarray(Ad),
        np.asarray(Bd),
        np.array([6.0, -3.0, 0.2, -0.4]),
        _Q2,
        _R2,
        N=SHAPE.N,
        Q_f=np.asarray(dare(Ad, Bd, _Q2, _R2)),
        u_max=0.3,  # |u_i| <= 0.3 N
        Fu=np.array([[1.0, 1.0], [1.0, -1.0]]),  # u_1 + u_2 <= 0.5, u_1 - u_2 <= 0.5
        fu=np.array([0.5, 0.5]),
        Fx=np.array([[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]),
        fx=np.array([4.5, 7.0, 1.0]),  # y >= -4.5, x <= 7, one padding row
        x_mask=np.array([1.0, 1.0, 0.0]),
        rho=1e4,
    )


_PLANAR_BASE = _make_planar_base()


def _planar_ocp(ts) -> OCP:
    """The planar OCP whose A, B and terminal weight Q_f follow from ts (traceable)."""
    Ac, Bc = planar2dof_continuous(_MASS)
    Ad, Bd = discretize_zoh(Ac, Bc, ts)
    P = dare(Ad, Bd, _Q2, _R2)
    base = _PLANAR_BASE
    return base._replace(
        A=jnp.broadcast_to(Ad, base.A.shape),
        B=jnp.broadcast_to(Bd, base.B.shape),
        Q=base.Q.at[-1].set(P),
    )


PLANAR_GRAD = jax.jit(jax.grad(lambda ts: _loss(_planar_ocp(ts))))


def test_grad_through_dare_and_discretisation():
    sol = _solve_fixed(_PLANAR_BASE)
    assert int(sol.status) == Status.CONVERGED
    assert np.max(np.abs(np.asarray(sol.u))) > 0.25  # the input bounds matter
    g = float(PLANAR_GRAD(_TS))
    fd = _fd(lambda t: _loss_value(_planar_ocp(_TS + t)), 1e-3)
    assert np.isfinite(g) and abs(g) > 1e-6
    _assert_directional(g, fd, abs(g), "d loss / d ts")


def test_kappa_is_traced_batched_and_differentiable():
    """kappa is a traced solver parameter: one compiled program serves every value (batched
    with vmap, no retrace), and d(loss)/d(kappa) through the implicit derivative matches
    central differences of converged solves."""
    ocp = _case("rows-active")
    traces = []

    def loss(kappa):
        traces.append(1)  # Python side effect: runs once per trace
        sol = solve(ocp, SETTINGS, params=PARAMS._replace(kappa=kappa))
        return jnp.sum(W_U * sol.u) + jnp.sum(W_X * sol.x)

    f = jax.jit(loss)
    values = [float(f(k)) for k in (0.3, 0.5, 0.8)]
    assert len(traces) == 1  # three values, one trace
    batched = jax.jit(jax.vmap(loss))(jnp.array([0.3, 0.5, 0.8]))
    np.testing.assert_allclose(np.asarray(batched), values, rtol=1e-9)
    g = float(jax.jit(jax.grad(loss))(0.5))
    h = 1e-5
    fd = (f(0.5 + h) - f(0.5 - h)) / (2 * h)
    assert abs(g) > 1e-6  # kappa moves the barrier solution
    assert g == pytest.approx(float(fd), rel=1e-5)


UNROLLED = 8  # Newton iterations differentiated through


def _unrolled_loss(ocp: OCP, log_scales, start):
    """The loss after UNROLLED full Newton steps of the fixed-kappa barrier problem from
    ``start`` (held constant), differentiated by ordinary reverse mode through the scan: no
    custom VJP, no implicit function theorem."""
    from rvdjax.solver.barrier import dyn_residual, gradient, hessian, objective, rows_of
    from rvdjax.solver.kkt import kkt_factor, kkt_solve

    o = _scaled(ocp, log_scales)
    rows = rows_of(o)

    def newton(z, _):
        u, x = z
        Phi_u, Phi_x = hessian(o, rows, u, x, PARAMS.kappa)
        g_u, g_x = gradient(o, rows, u, x, PARAMS.kappa)
        kkt = kkt_factor(o.A, o.B, Phi_u, Phi_x, "riccati")
        step = kkt_solve(kkt, g_u, g_x, dyn_residual(o, u, x), "riccati")
        return (u + step.du, x + step.dx), None

    (u, x), _ = jax.lax.scan(newton, start, None, length=UNROLLED)
    return jnp.sum(W_U * u) + jnp.sum(W_X * x) + 1e-2 * objective(o, u, x)  # as _loss


UNROLLED_GRAD = jax.jit(jax.grad(_unrolled_loss, argnums=1))


def test_implicit_derivative_equals_unrolled_iterations(case):
    """The implicit derivative of the solve equals reverse mode through UNROLLED Newton
    iterations started near the solution (the solution of the problem with both weights 5 %
    larger, held constant): Newton converges quadratically, so the unrolled map's derivative
    reaches the fixed point's, which the implicit function theorem gives in one solve."""
    name, ocp, _, _ = case
    w0 = jnp.zeros(2)
    near = _solve_fixed(_scaled(ocp, w0 + 0.05))
    start = (near.u, near.x)
    g_impl = np.asarray(GRAD_SCALED(ocp, w0))
    g_unrolled = np.asarray(UNROLLED_GRAD(ocp, w0, start))
    # the unrolled iterate reached the solution
    loss = _loss_value(ocp)
    assert abs(float(_unrolled_loss(ocp, w0, start)) - loss) <= 1e-10 * (1.0 + abs(loss))
    np.testing.assert_allclose(g_unrolled, g_impl, rtol=1e-7, atol=1e-9 * np.abs(g_impl).max())
