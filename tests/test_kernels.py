"""The Newton step's GPU kernels (rvdjax.solver.lanes) inside the solver: interpreted on the
CPU they give today's iterates, statuses, iteration counts and derivatives; compiled for a
CUDA GPU (lowered here, no GPU needed) the Riccati sweeps are a few kernels per iteration
and no loop over stages is left in the iteration."""

from __future__ import annotations

import dataclasses
import functools
import re

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest
from ocp_factory import SHAPE_CLASSES, random_ocp

from rvdjax.problems import fastmpc3d_first_step, stack_ocps
from rvdjax.solver import (
    SolverParams,
    SolverSettings,
    Status,
    iterate,
    lanes,
    solve,
    start,
    tracing_for_cuda,
)
from rvdjax.solver.platform import AUTO_ON_CUDA

# Problems are padded to a tile of ``block`` lanes: a small tile keeps the interpreter cheap.
BLOCK = 8
# the tables' index among a kernel's inputs for a batch of three: one tile of four lanes (a
# batch smaller than a tile runs in one tile of the next power of two)
INDEX_OF_3 = "int32[4]"


@functools.cache
def _solver(settings: SolverSettings):
    return jax.jit(jax.vmap(lambda o: solve(o, settings)))


@pytest.fixture(autouse=True, scope="module")
def _small_tiles():
    """Every kernel of this module traced with tiles of BLOCK lanes (set once: a change of
    the launch configuration clears JAX's caches)."""
    with lanes.configured(block=BLOCK):
        yield


def _solve(settings, ocps):
    return _solver(settings)(ocps)


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.linalg.norm(a - b) / max(np.linalg.norm(a), 1e-300)


def _fastmpc_pair():
    o = fastmpc3d_first_step(obstacles=True)
    return stack_ocps([o, o._replace(x_mask=jnp.zeros_like(o.x_mask))])


CASES = {
    "fastmpc-3d accurate": (SolverSettings, _fastmpc_pair),
    "small accurate": (SolverSettings, lambda: _random("small", 4)),
    "small paper": (SolverSettings.paper, lambda: _random("small", 4)),
}


def _random(name, n):
    return stack_ocps([random_ocp(seed, SHAPE_CLASSES[name]) for seed in range(n)])


# The default GPU form in every run on the random classes (accurate and paper mode); on
# fastmpc-3d (30 stages, obstacles: 31-39 s of the suite on a 2-core VM without AVX-512), the
# opt-in kernel forms and the unrolled loops in the slow run (the suite's 10 minutes on 2 cores).
@pytest.mark.parametrize(
    "kernel",
    [
        *(
            pytest.param(k, marks=pytest.mark.slow)
            for k in (
                "pallas",
                "pallas-block-io",
                "pallas-fused",
                "pallas-block-factor",
                "pallas-block-fused",
            )
        ),
        pytest.param("pallas-block-rows", marks=pytest.mark.slow),
        pytest.param("pallas-rows", marks=pytest.mark.slow),
        pytest.param("pallas-entries", marks=pytest.mark.slow),
        "pallas-carried",
        pytest.param("unrolled", marks=pytest.mark.slow),  # opt-in; its gradients checked below
    ],
)
@pytest.mark.parametrize(
    "case",
    [pytest.param(c, marks=pytest.mark.slow) if c.startswith("fastmpc") else c for c in CASES],
)
def test_kernels_give_the_xla_iterates(case, kernel):
    """The Pallas kernels (interpreted; the factorisation and the first step in one kernel or in
    two, the corrector's step and its refinement in one kernel or in two, a stage's arrays
    loaded and stored entry by entry or as blocks, the row work between the solves in a
    kernel of its own or in XLA's fusions) and the unrolled XLA
    loops against XLA's loops. The same statuses and iteration counts, and the same answer: to
    1e-10 relative (in norm) in the plan and the multipliers. Both forms round differently
    (fused products, summation inside the kernel), and the Newton matrix's conditioning
    amplifies rounding as the gap closes: on fastmpc-3d the iterates agree to 1e-16 at the first
    iterations and to ~1e-11 at the ninth, where the XLA form's own batched and unbatched solves
    differ by 2.5e-12 (docs/solver.md). In accurate mode the objective is Clarabel's to 1e-7."""
    make, ocps = CASES[case]
    ocps = ocps()
    xla = _solve(make(kernel="xla"), ocps)
    pal = _solve(make(kernel=kernel), ocps)
    np.testing.assert_array_equal(np.asarray(pal.status), np.asarray(xla.status))
    np.testing.assert_array_equal(np.asarray(pal.iterations), np.asarray(xla.iterations))
    assert set(np.asarray(xla.status).tolist()) <= {Status.CONVERGED, Status.MAX_ITER}
    for name in ("u", "x", "nu"):
        assert _rel(getattr(xla, name), getattr(pal, name)) <= 1e-10, name
    np.testing.assert_allclose(np.asarray(pal.objective), np.asarray(xla.objective), rtol=1e-12)
    if make is SolverSettings:  # accurate mode: Clarabel's optimum of the same QPs
        ref = _solver(SolverSettings(backend="clarabel"))(ocps)
        np.testing.assert_allclose(np.asarray(pal.objective), np.asarray(ref.objective), rtol=1e-7)


def _random_rows_inputs(key, rows=None, N=5, mx=3, mu=4, nx=6, nu=3):
    """Inputs of pd_algebra._corrector_rhs for one problem: rows with masked entries (or
    ``rows``), a strictly interior iterate (s > 0, s > g, su > 0, positive multipliers), a
    random step."""
    from rvdjax.solver.barrier import Rows
    from rvdjax.solver.primal_dual import PDState
    from rvdjax.solver.riccati import NewtonStep

    k = iter(jax.random.split(key, 32))

    def normal(*shape):
        return jax.random.normal(next(k), shape, jnp.float64)

    def positive(*shape):
        return jnp.exp(normal(*shape))

    wx = (jax.random.uniform(next(k), (N, mx)) > 0.2).astype(jnp.float64)
    wu = (jax.random.uniform(next(k), (N, mu)) > 0.2).astype(jnp.float64)
    drawn = Rows(normal(N, mu, nu), positive(N, mu), wu, normal(N, mx, nx), positive(N, mx), wx,
                 10.0 * positive(N, mx))  # fmt: skip
    rows = drawn if rows is None else rows
    s = positive(N, mx)
    g = s - positive(N, mx)  # s - g > 0
    su = positive(N, mu)
    zero = jnp.zeros((), jnp.float64)
    st = PDState(normal(N, nu), normal(N, nx), normal(N, nx), s, positive(N, mu),
                 positive(N, mx), positive(N, mx), jnp.asarray(3), jnp.asarray(False),
                 jnp.asarray(1), 5.0 + zero, 20.0 * jax.random.uniform(next(k)), su, g)  # fmt: skip
    sx = s - g
    step = NewtonStep(normal(N, nu), normal(N, nx), normal(N, nx))
    h = 0.0 / sx + 0.0 / s - rows.rho
    m_eff = jnp.sum(wu) + 2.0 * jnp.sum(wx)
    return (rows, st, normal(N, nu), normal(N, nx), su, sx, step, h, m_eff)


# The row kernels read and write a stage entry by entry (the default on a GPU) or as blocks
# (``"pallas-block-rows"``, in the slow run): the same arithmetic, other loads and stores.
ROW_IO = pytest.mark.parametrize(
    "block_io", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["entries", "blocks"]
)


@ROW_IO
def test_the_rows_kernel_forms_the_xla_corrector_rhs(block_io):
    """The accurate mode's row work between its two solves as one kernel
    (rvdjax.solver.rows_kernel, interpreted), against XLA's form (pd_algebra._corrector_rhs)
    on random interior iterates with masked rows: one problem and a vmapped batch whose rows
    are shared (unbatched under vmap). The predictor's row products and step length agree to
    rounding, the corrector's barrier weight and right-hand side to 1e-12 relative: the kernel
    sums the complementarity after the step and the right-hand side as polynomials in the step
    length and the weight, then evaluates them (module docstring)."""
    from rvdjax.solver import pd_algebra as pa
    from rvdjax.solver import pd_kernels as pk

    def both(args):
        want = pa._corrector_rhs(*args)
        got = pk._rows_in_kernel(*args, interpret=True, block_io=block_io)
        return want, got

    def check(want, got):
        for name, w, g, tol in zip(
            ("g_u", "g_x", "Fdu", "Fdx", "alpha_a", "kappa"),
            want,
            got,
            (1e-12, 1e-12, 1e-14, 1e-14, 1e-15, 1e-12),
            strict=True,
        ):
            assert _rel(w, g) <= tol, name

    for seed in range(3):
        args = _random_rows_inputs(jax.random.key(seed))
        want, got = jax.jit(both)(args)
        assert 0.0 < float(want[4]) <= 1.0 and float(want[5]) > 0.0  # a cut step, a weight
        check(want, got)
    # a batch of iterates sharing the rows (the Fu, Fx, masks of one problem)
    rows = _random_rows_inputs(jax.random.key(10))[0]
    batch = [_random_rows_inputs(jax.random.key(10 + i), rows) for i in range(3)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *[b[1:] for b in batch])
    axes = (None,) + (0,) * len(stacked)
    want, got = jax.jit(jax.vmap(lambda *a: both(a), in_axes=axes))(rows, *stacked)
    check(want, got)


def _random_cost(key, N=5, nx=6, nu=3, model=None, cost=None):
    """The cost and the model of one problem (an OCP with only those fields and the initial
    state): random SPD blocks Q, R, model A, B, c, linear costs, reference and initial state;
    ``model`` = (A, B) and ``cost`` = (Q, R) given instead where not None."""
    from rvdjax.ocp import OCP

    k = iter(jax.random.split(key, 12))

    def normal(*shape):
        return jax.random.normal(next(k), shape, jnp.float64)

    def spd(n):
        X = normal(N, n, n)
        return X @ jnp.swapaxes(X, -1, -2) + n * jnp.eye(n)

    A, B = (normal(N, nx, nx), normal(N, nx, nu)) if model is None else model
    Q, R = (spd(nx), spd(nu)) if cost is None else cost
    c, x0, none = normal(N, nx), normal(nx), (None,) * 7
    return OCP(A, B, c, x0, Q, R, normal(N, nx), normal(N, nx), normal(N, nu), *none)


def _step_case(key, nan, stop, emphasis, shared=None):
    """Arguments of pd_algebra._step_xla (ocp, rows, st, su, sx, step, taus, h, fraction) and
    the predictor's (Fdu_a, Fdx_a, alpha_a, kappa) the step's kernel takes too: a random
    interior iterate, the predictor's row products and a random corrector step, a NaN in the
    step's multipliers (``nan``), a random step fraction in [0.99, 0.9999], 0 where ``stop``
    (a stopped solve's); ``emphasis`` 0-3 scales one stage's model or
    multipliers by 1e3 (test_the_step_kernel_takes_the_xla_step); ``shared`` the cost and
    model instead of a random one."""
    from rvdjax.solver import pd_algebra as pa
    from rvdjax.solver import stagewise as sw

    rows, st, _, _, su, sx, step, h_pred, _ = _random_rows_inputs(key)
    k1, k2, k3, k4 = jax.random.split(jax.random.fold_in(key, 7), 4)
    ocp = _random_cost(k3) if shared is None else shared
    big = jnp.where(jnp.arange(4) == emphasis, 1e3, 1.0)
    # emphasis 2: the last stage's multipliers 1e3 larger, its model 1e3 smaller
    ocp = ocp._replace(
        A=ocp.A.at[1].multiply(big[0]).at[-1].multiply(big[1] / big[2]),
        B=ocp.B.at[0].multiply(big[3]).at[-1].divide(big[2]),
    )
    st = st._replace(nu=st.nu.at[-1].multiply(big[2]))
    step = step._replace(nu=step.nu.at[-1].multiply(big[2]))
    pred = jax.random.normal(k1, step.dx.shape, jnp.float64)
    Fdu_a = sw.mv(rows.Fu, jax.random.normal(k2, step.du.shape, jnp.float64))
    Fdx_a = sw.mv(rows.Fx, pred)
    alpha_a, kappa = jnp.asarray(0.7), jnp.asarray(0.05)
    zu, zx = jnp.zeros_like(su), jnp.zeros_like(sx)
    aff = pa._row_steps(rows, st, Fdu_a, Fdx_a, su, sx, zu, zx, zx, h_pred)
    taus = pa._targets(aff, alpha_a, kappa)
    h = pa._soft_h(rows, st, sx, taus[1], taus[2])
    step = step._replace(nu=jnp.where(nan, step.nu.at[2, 1].set(jnp.nan), step.nu))
    fraction = jnp.where(stop, 0.0, jax.random.uniform(k4, (), jnp.float64, 0.99, 0.9999))
    return (ocp, rows, st, su, sx, step, taus, h, fraction), (Fdu_a, Fdx_a, alpha_a, kappa)


@ROW_IO
def test_the_step_kernel_takes_the_xla_step(block_io):
    """The corrector's row work as one kernel (rows_kernel.pd_step_rows, interpreted):
    pd_kernels._step_in_kernel against XLA's pd_algebra._step_xla from random interior
    iterates, the predictor's row products and a random corrector step, eight problems of a
    batch: the new iterate, the complementarity there and the stopping test's relative dual
    residual and objective there to 1e-12 relative (the kernel sums the complementarity as a
    polynomial in the step length, and the stopping test stage by stage). The dual residual is
    a maximum over every stage's rows: four problems scale one stage's model (or multipliers)
    by 1e3 so that the maximum is the state residual of the first stage (A_1^T nu_1, carried
    one stage in the kernel), of the last but one, of the last (no next stage) and the input
    residual of the first. A step with a NaN (in the multipliers nu, which no row's step
    reads: the kernel tests the step itself) is refused by both (the iterate kept), and so is
    a stopped solve's. A batch that shares its cost and model (the batch engine's) gives the
    same as XLA too."""
    from rvdjax.solver import pd_algebra as pa
    from rvdjax.solver import pd_kernels as pk

    def case(key, nan, stop, emphasis, shared=None):
        args, rows_a = _step_case(key, nan, stop, emphasis, shared)
        want = pa._step_xla(*args)
        got = pk._step_in_kernel(*args, aff=rows_a, interpret=True, block_io=block_io)
        return args[2], want, got

    # eight problems of one batch: steps taken, one with a NaN, one stopped, four emphases
    nan = np.array([False, False, True, False, False, False, False, False])
    stop = np.array([False, False, False, True, False, False, False, False])
    emphasis = jnp.asarray([-1, -1, -1, -1, 0, 1, 2, 3])
    keys = jax.random.split(jax.random.key(0), 8)
    out = jax.jit(jax.vmap(case))(keys, jnp.asarray(nan), jnp.asarray(stop), emphasis)
    rel_d = []
    for i in range(8):
        st, want, got = jax.tree.map(lambda a, i=i: a[i], out)
        (new_w, gap_w, fin_w, stop_w) = want
        (new_g, gap_g, fin_g, stop_g) = got
        assert bool(fin_w) == bool(fin_g) == (not nan[i])
        for w, g in zip(new_w, new_g, strict=True):
            assert _rel(w, g) <= 1e-12
        for w, g in ((gap_w, gap_g), *zip(stop_w, stop_g, strict=True)):
            assert _rel(w, g) <= 1e-12, i
        assert float(stop_g[0]) > 0.0 and abs(float(stop_g[1])) > 0.0  # sums that could differ
        rel_d.append(float(stop_w[0]))
        if nan[i] or stop[i]:  # a step of length zero: the iterate kept
            np.testing.assert_array_equal(np.asarray(new_g[3]), np.asarray(st.s))
        else:
            assert _rel(new_g[3], st.s) > 1e-3  # a step taken
    assert min(rel_d[4:]) > 10.0 * max(rel_d[:4])  # each emphasis sets the maximum
    # a batch sharing its cost and model: read as a table of one, and q, r, x_ref as scalars
    shared = _random_cost(jax.random.key(9))
    run = jax.vmap(lambda key: case(key, False, False, -1, shared)[1:])
    (call,) = [
        str([v.aval for v in e.invars])
        for e in _eqns(jax.make_jaxpr(run)(keys[:3]).jaxpr)
        if e.primitive.name == "pallas_call"
    ]
    assert INDEX_OF_3 in call and call.count("float64[5,6]") == 2  # index; q, x_ref
    for want, got in zip(*jax.jit(run)(keys[:3]), strict=True):
        for w, g in zip(jax.tree.leaves(want), jax.tree.leaves(got), strict=True):
            assert _rel(np.asarray(w, float), np.asarray(g, float)) <= 1e-12


@ROW_IO
def test_the_step_kernel_forms_the_next_newton_system(block_io):
    """The step's kernel that carries the Newton system ("pallas-carried";
    pd_kernels._step_in_kernel with ``system``, interpreted): the same step, complementarity,
    stopping test and finiteness as the kernel without it, and the Newton system at the new
    iterate that the blocks' kernel forms from it (rows_kernel.pd_blocks), both to 1e-15
    relative (the same arithmetic; the compiler contracts a product and a sum into one
    rounding in some places and not in others: Phi_x differed in the last bit in 17 of 105
    entries), and XLA's (pd_algebra._system_xla) to 1e-12 relative: steps taken, one with a
    NaN and one stopped
    (both keep the iterate), and a batch sharing its cost and model (the dynamics' offset c
    read as scalars). The carried kernel forms the corrector's row products and the rows'
    dual-residual terms again in its second sweep instead of storing them in its first."""
    from rvdjax.solver import pd_algebra as pa
    from rvdjax.solver import pd_kernels as pk

    def case(key, nan, stop, shared=None):
        args, rows_a = _step_case(key, nan, stop, -1, shared)
        ocp, rows, st = args[:3]
        kernel = functools.partial(pk._step_in_kernel, aff=rows_a, interpret=True)
        plain = kernel(*args, block_io=block_io)
        *carried, system = kernel(*args, block_io=block_io, system=True)
        u, x, nu, s, lam, mu, pi, su, g = carried[0]
        at = st._replace(u=u, x=x, nu=nu, s=s, lam=lam, mu=mu, pi=pi, su=su, g=g)
        blocks = pk._system_in_kernel(ocp, rows, at, su, s - g, True, block_io=block_io)
        return plain, carried, system, blocks, pa._system_xla(ocp, rows, at, su, s - g), st.s

    def check(plain, carried, system, blocks, xla, _):
        for p, c in zip(jax.tree.leaves(plain), jax.tree.leaves(carried), strict=True):
            assert _rel(np.asarray(p, float), np.asarray(c, float)) <= 1e-15
        for got, by_blocks, want in zip(system, blocks, xla, strict=True):
            assert _rel(by_blocks, got) <= 1e-15
            assert _rel(want, got) <= 1e-12

    nan, stop = jnp.asarray([False, True, False]), jnp.asarray([False, False, True])
    keys = jax.random.split(jax.random.key(20), 3)
    out = jax.jit(jax.vmap(case))(keys, nan, stop)
    for i in range(3):
        check(*jax.tree.map(lambda a, i=i: a[i], out))
    assert _rel(out[1][0][3][0], out[-1][0]) > 1e-3  # the first step moved its iterate
    shared = _random_cost(jax.random.key(21))
    run = jax.vmap(lambda key: case(key, False, False, shared))
    calls = [e for e in _eqns(jax.make_jaxpr(run)(keys).jaxpr) if e.primitive.name == "pallas_call"]
    # q, x_ref (and c, with the system) without a problem axis
    assert [str([v.aval for v in e.invars]).count("float64[5,6]") for e in calls[:2]] == [2, 3]
    # the first sweep's row products Fu du, Fx dx and the rows' terms (U, X): written for the
    # second sweep by the plain kernel (5 stages each), formed again by the carried one, whose
    # outputs for them are (1, 1) placeholders
    plain, carried = ([v.aval.shape[:2] for v in e.outvars[:4]] for e in calls[:2])
    assert [s[0] for s in plain] == [5] * 4 and carried == [(1, 1)] * 4
    check(*jax.jit(run)(keys))


@ROW_IO
def test_the_blocks_kernel_forms_the_xla_newton_blocks(block_io):
    """The predictor's Newton blocks as one kernel (rows_kernel.pd_blocks, interpreted):
    Phi_u, Phi_x (the lower triangles it writes, and the matrices mirrored from them), the
    right-hand side, the cost's gradient and the dynamics' residual against XLA's
    pd_algebra._newton_blocks to 1e-12 relative, from random interior iterates with masked
    rows: one problem; a vmapped batch whose cost is shared (the blocks read as a table of
    one, the linear costs, the reference and the dynamics' offset as scalars); and a batch
    reading its input rows, soft rows' mask and penalty, cost blocks and model from tables of
    K = 3 at each problem's index (the batch engine's phase tables)."""
    from rvdjax.solver import pd_algebra as pa
    from rvdjax.solver import pd_kernels as pk
    from rvdjax.solver.lanes import tri_pack
    from rvdjax.solver.riccati import ModelTable, SymStored

    N, mx, mu, K = 5, 3, 4, 3
    k = iter(jax.random.split(jax.random.key(40), 8))

    def args_of(key, rows=None, cost=None):
        rows_, st, _, _, su, sx, _, _, _ = _random_rows_inputs(key, rows, N, mx, mu)
        ocp = _random_cost(jax.random.fold_in(key, 3), N) if cost is None else cost
        return (ocp, rows_, st, su, sx)

    def check(want, got):
        for w, g in zip(want, got, strict=True):
            if isinstance(g, SymStored):  # Phi_u, Phi_x: the triangles the kernel wrote
                assert _rel(tri_pack(w, -2), g.lower) <= 1e-12
                g = g.whole
            assert _rel(w, g) <= 1e-12

    def both(a, table=None):
        got = pk._blocks_in_kernel(*a, interpret=True, table=table, block_io=block_io)
        return pa._newton_blocks(*a), got

    one = args_of(jax.random.key(41))
    check(*jax.jit(both)(one))
    # a batch sharing its cost: the blocks a table of one, q, r, x_ref read as scalars
    shared = _random_cost(next(k), N)
    batch = [args_of(jax.random.key(42 + i))[1:] for i in range(3)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *batch)
    run = jax.vmap(lambda a: both((shared, *a)))
    jaxpr = jax.make_jaxpr(run)(stacked).jaxpr
    calls = [
        str([v.aval for v in e.invars]) for e in _eqns(jaxpr) if e.primitive.name == "pallas_call"
    ]
    assert len(calls) == 1 and INDEX_OF_3 in calls[0]
    assert calls[0].count(f"float64[{N},6]") == 3  # q, x_ref and c, without a problem axis
    want, got = jax.jit(run)(stacked)
    check(want, got)
    # the phase tables: each problem's rows and blocks are entries of the tables
    Fu_t = jax.random.normal(next(k), (K, N, mu, 3), jnp.float64)
    wx_t = (jax.random.uniform(next(k), (K, N, mx)) > 0.3).astype(jnp.float64)
    rho_t = jnp.where(wx_t > 0, 10.0 * jnp.exp(jax.random.normal(next(k), (K, N, mx))), 1.0)
    models = jax.vmap(lambda key: _random_cost(key, N))(jax.random.split(next(k), K))
    index = jnp.asarray([2, 0, 1])
    cases = []
    for i in range(3):
        ocp, r, *rest = args_of(jax.random.key(50 + i))
        at = int(index[i])
        rows = r._replace(
            Fu=jnp.where(r.wu[..., None] > 0, Fu_t[at], 0.0), wx=wx_t[at], rho=rho_t[at]
        )
        one = jax.tree.map(lambda a, at=at: a[at], models)
        cases.append((ocp._replace(A=one.A, B=one.B, Q=one.Q, R=one.R), rows, *rest))
    batch = jax.tree.map(lambda *a: jnp.stack(a), *cases)
    M_t = jnp.concatenate([models.B, models.A], axis=-1)
    table = ModelTable(M_t, index, Fu_t, wx_t, rho_t, models.Q, models.R)
    axes = (ModelTable(None, 0, None, None, None, None, None), 0)
    want, got = jax.jit(jax.vmap(lambda t, a: both(a, t), in_axes=axes))(table, batch)
    check(want, got)


@ROW_IO
def test_the_row_kernels_read_the_phase_tables_as_the_rows_they_stand_for(block_io):
    """With the input rows and the soft rows' mask and penalty (and, for the step's kernel,
    the cost blocks and the model [B, A]) given as tables of K = 3 and each problem's index
    (the batch engine's phase tables; the input rows before the problem's own mask zeroes
    some of them), both row kernels (interpreted, under vmap) compute, bit for bit, what they
    compute from each problem's rows."""
    from rvdjax.solver import pd_algebra as pa
    from rvdjax.solver import pd_kernels as pk
    from rvdjax.solver.riccati import ModelTable

    N, mx, mu, K, b = 5, 3, 4, 3, 3
    k = iter(jax.random.split(jax.random.key(20), 8))
    Fu_t = jax.random.normal(next(k), (K, N, mu, 3), jnp.float64)
    wx_t = (jax.random.uniform(next(k), (K, N, mx)) > 0.3).astype(jnp.float64)
    rho_t = jnp.where(wx_t > 0, 10.0 * jnp.exp(jax.random.normal(next(k), (K, N, mx))), 1.0)
    models = jax.vmap(lambda key: _random_cost(key, N))(jax.random.split(next(k), K))
    M_t = jnp.concatenate([models.B, models.A], axis=-1)
    index = jnp.asarray([2, 0, 2])
    cases, costs = [], []
    for i in range(b):
        args = _random_rows_inputs(jax.random.key(30 + i), N=N, mx=mx, mu=mu)
        r = args[0]
        at = int(index[i])
        rows = r._replace(
            Fu=jnp.where(r.wu[..., None] > 0, Fu_t[at], 0.0), wx=wx_t[at], rho=rho_t[at]
        )
        assert 0 < float(jnp.sum(r.wu)) < r.wu.size  # some input rows zeroed by the mask
        cases.append((rows, *args[1:]))
        one = jax.tree.map(lambda a, at=at: a[at], models)
        costs.append(
            _random_cost(jax.random.key(60 + i), N, model=(one.A, one.B), cost=(one.Q, one.R))
        )
    batch = jax.tree.map(lambda *a: jnp.stack(a), *cases)
    cost = jax.tree.map(lambda *a: jnp.stack(a), *costs)

    def both(table, cost, *args):
        plain = pk._rows_in_kernel(*args, interpret=True, block_io=block_io)
        tabled = pk._rows_in_kernel(*args, interpret=True, table=table, block_io=block_io)
        rows, st, _, _, su, sx, step, h, _ = args
        Fdu_a, Fdx_a, alpha_a, kappa = plain[2:]
        taus = pa._targets(
            pa._row_steps(rows, st, Fdu_a, Fdx_a, su, sx, 0 * su, 0 * sx, 0 * sx, h),
            alpha_a,
            kappa,
        )
        h_c = pa._soft_h(rows, st, sx, taus[1], taus[2])
        step_args = (cost, rows, st, su, sx, step, taus, h_c, jnp.asarray(False))
        aff = (Fdu_a, Fdx_a, alpha_a, kappa)
        steps = [
            pk._step_in_kernel(*step_args, aff=aff, interpret=True, table=t, block_io=block_io)
            for t in (None, table)
        ]
        return (plain, *steps[:1]), (tabled, *steps[1:])

    table = ModelTable(M_t, index, Fu_t, wx_t, rho_t, models.Q, models.R)
    axes = (ModelTable(None, 0, None, None, None, None, None), *(0,) * (len(batch) + 1))
    run = jax.vmap(both, in_axes=axes)
    calls = [
        [str(v.aval) for v in e.invars]
        for e in _eqns(jax.make_jaxpr(run)(table, cost, *batch).jaxpr)
        if e.primitive.name == "pallas_call"
    ]
    with_index = [c for c in calls if INDEX_OF_3 in c]
    assert len(calls) == 4 and len(with_index) == 2  # each kernel once with the tables
    assert all(f"float64[{K},{N},{mu * 3}]" in c for c in with_index)
    plain, tabled = jax.jit(run)(table, cost, *batch)
    leaves = jax.tree.leaves(plain)
    assert len(leaves) > 10
    for a, t in zip(leaves, jax.tree.leaves(tabled), strict=True):
        np.testing.assert_array_equal(np.asarray(t), np.asarray(a))


@pytest.mark.slow  # the kernels are opt-in; 15-20 s
def test_one_iteration_from_the_same_iterate_agrees_to_rounding():
    """From the same iterate, one accurate-mode iteration with either form lands on the same
    next iterate to 1e-13 relative while the problem is well conditioned (the first five
    iterations of fastmpc-3d, gap above 1e3 times the tolerance; later ones are covered by
    the whole solves above)."""
    ocps = _fastmpc_pair()
    params = SolverParams()
    xs, ps = SolverSettings(kernel="xla"), SolverSettings(kernel="pallas")

    def xla_iterates(o):  # the XLA form's first five iterates, stacked
        oc, st = start(o, xs, params)

        def body(st, _):
            return iterate(oc, xs, params, st), st

        return oc, jax.lax.scan(body, st, length=5)[1]

    ocs, states = jax.jit(jax.vmap(xla_iterates))(ocps)
    ocs = jax.tree.map(lambda a: jnp.repeat(a[:, None], 5, axis=1), ocs)

    def step(settings):
        one = lambda oc, st: iterate(oc, settings, params, st).core  # noqa: E731
        return jax.jit(jax.vmap(jax.vmap(one)))

    a = step(xs)(ocs, states)
    b = step(ps)(ocs, states)
    for name in ("u", "x", "nu", "lam", "mu", "pi", "s"):
        for k in range(5):
            assert _rel(getattr(a, name)[:, k], getattr(b, name)[:, k]) <= 1e-13, (name, k)


def test_kernel_gradients_match_central_differences():
    """Reverse mode through a solve whose Newton steps and implicit derivative (its adjoint
    solve) run in the kernels: the XLA form's gradient, and central differences. Paper mode
    at a fixed kappa solved to convergence, as in test_gradients (a well-conditioned
    barrier point; accurate mode's tight point amplifies rounding in either form)."""
    ocp = random_ocp(3, SHAPE_CLASSES["small"])
    params = SolverParams(kappa=0.5, tol=1e-13)

    def loss(settings, scale, x0):
        o = ocp._replace(x0=x0, R=ocp.R * scale)
        sol = solve(o, settings, params=params)
        return sol.objective + jnp.sum(sol.u**2)

    grads, fds = {}, {}
    h = 1e-5
    for kernel in ("xla", "pallas", "unrolled"):
        settings = SolverSettings.paper(kernel=kernel, max_iter=200)
        f = jax.jit(functools.partial(loss, settings))
        grads[kernel] = jax.jit(jax.grad(functools.partial(loss, settings), (0, 1)))(1.3, ocp.x0)
        fds[kernel] = (float(f(1.3 + h, ocp.x0)) - float(f(1.3 - h, ocp.x0))) / (2 * h)
    gs_x, g0_x = grads["xla"]
    for kernel in ("pallas", "unrolled"):
        gs_p, g0_p = grads[kernel]
        assert float(gs_p) == pytest.approx(float(gs_x), rel=1e-9), kernel
        np.testing.assert_allclose(np.asarray(g0_p), np.asarray(g0_x), rtol=1e-9)
        assert float(gs_p) == pytest.approx(fds[kernel], rel=1e-6), kernel
        assert fds[kernel] == pytest.approx(fds["xla"], rel=1e-8), kernel


@pytest.mark.parametrize(
    "form",
    [
        "block",
        pytest.param("block-refined", marks=pytest.mark.slow),  # interpreted: 5 s more
        pytest.param("entries", marks=pytest.mark.slow),  # entry by entry: opt-in forms
    ],
)
def test_the_kernels_read_a_model_table_as_the_copies_it_stands_for(form):
    """Given a table of models and each problem's index (the batch engine's phase models),
    the Riccati kernels (interpreted) compute, bit for bit, what they compute from the [B, A]
    copy each problem would otherwise carry, with block loads (and their refinement) and
    entry by entry; the solver's form for a CUDA GPU passes them the table and not the
    copies (the factorisation's flattened for its block loads, the refined solve's as it is,
    read entry by entry)."""
    from rvdjax.solver import riccati

    rng = np.random.default_rng(3)
    N, nx, nu, K, b = 2, 6, 3, 3, 11  # two tiles, the second padded
    table = jnp.asarray(0.3 * rng.normal(size=(K, N, nx, nu + nx)))
    index = jnp.asarray([0, 2, 1, 2, 2, 0, 1, 1, 0, 2, 1])
    M = jnp.moveaxis(table[index], 0, -1)

    def spd(n):
        X = rng.normal(size=(N, n, n, b))
        return jnp.asarray(np.einsum("tijb,tkjb->tikb", X, X) + n * np.eye(n)[..., None])

    Pu_whole, Px_whole = spd(nu), spd(nx)
    Pu, Px = (lanes.tri_pack(a, 1) for a in (Pu_whole, Px_whole))  # the kernels' storage
    rhs = [jnp.asarray(rng.normal(size=(N, n, b))) for n in (nu, nx, nx)]
    block_io = form != "entries"
    cfg = dataclasses.replace(lanes.default_config(), interpret=True, block_io=block_io)
    f, s = lanes.factor_solve(M, Pu, Px, *rhs, cfg)
    f_t, s_t = lanes.factor_solve(table, Pu, Px, *rhs, cfg, index=index)
    outs = [*f, *s], [*f_t, *s_t]
    step = step_t = ()
    if form == "block-refined":  # the solver's form on a GPU
        step = lanes.apply_refined(M, *f, Pu, Px, *rhs, cfg)
        step_t = lanes.apply_refined(table, *f, Pu, Px, *rhs, cfg, index=index)
    for a, t in zip([*outs[0], *step], [*outs[1], *step_t], strict=True):
        np.testing.assert_array_equal(np.asarray(t), np.asarray(a))
    if form != "block":
        return

    def solve_both(A, B, Pu, Px, gu, gx, rp, i):
        kkt, s = riccati.riccati_factor_solve(A, B, Pu, Px, gu, gx, rp, AUTO_ON_CUDA, (table, i))
        return riccati.riccati_apply_refined(kkt, Pu, Px, gu, gx, rp, AUTO_ON_CUDA, (table, i))

    first = [jnp.moveaxis(a, -1, 0) for a in (Pu_whole, Px_whole, *rhs)]
    args = (table[index][..., nu:], table[index][..., :nu], *first, index)
    with tracing_for_cuda():
        jaxpr = jax.make_jaxpr(jax.vmap(solve_both))(*args)
    models = [
        [str(v.aval) for v in e.invars[:2]]
        for e in _eqns(jaxpr.jaxpr)
        if e.primitive.name == "pallas_call" and "riccati" in str(e.params["name"])
    ]
    lanes_ = f"int32[{-(-b // BLOCK) * BLOCK}]"
    flat = [f"float64[{K},{N},{nx * (nu + nx)}]", lanes_]  # the factorisation's block loads
    entries = [f"float64[{K},{N},{nx},{nu + nx}]", lanes_]  # the refined solve's, by entry
    assert models == [flat, flat, entries, entries], models  # CPU's and CUDA's of each


def _eqns(jaxpr):
    for e in jaxpr.eqns:
        yield e
        for sub in jax.extend.core.jaxprs_in_params(e.params):
            yield from _eqns(sub)


def _cuda_text(fn, *args):
    with tracing_for_cuda():
        return jax.jit(fn).trace(*args).lower(lowering_platforms=("cuda",)).as_text()


def _triton_calls(text):
    """Each Triton launch of a lowered program: its configuration and kernel IR."""
    return [ln[ln.index("mhlo.backend_config") :] for ln in text.splitlines() if "gpu.triton" in ln]


@pytest.mark.parametrize(
    "settings, kernels, loops, variant",
    [
        # accurate: factorisation, then the predictor, corrector and refinement steps (in
        # "pallas-block-fused": the factorisation with the predictor's step, and the
        # corrector's step with its refinement; in "pallas-entries", "pallas-rows" and
        # "pallas-block-rows", the row work before, between and after them three more; in
        # "pallas-carried", the default on a GPU, the blocks' kernel at the start only, its
        # work in the step's kernel of each iteration); the forms whose rows run in kernels
        # run the start's drift of the warm-start inputs as one more;
        # loops: the solve alone (the drift is a kernel or unrolled on a GPU) (the opt-in
        # forms in the slow run, 3-5 s each; "auto" lowers the default GPU form)
        *(
            pytest.param(SolverSettings(), 4, 1, v, marks=pytest.mark.slow)
            for v in ("pallas", "pallas-block-io", "pallas-block-factor")
        ),
        pytest.param(SolverSettings(), 2, 1, "pallas-block-fused", marks=pytest.mark.slow),
        pytest.param(SolverSettings(), 6, 1, "pallas-block-rows", marks=pytest.mark.slow),
        # the Newton system formed by the start's blocks kernel, then by the step's
        pytest.param(SolverSettings(), 6, 1, "pallas-carried", marks=pytest.mark.slow),
        # the default form: the start's blocks and drift kernels, then four an iteration
        (SolverSettings(), 6, 1, "auto"),
        # paper: factorisation + step, and the drift's kernel in "auto"; loops: the solve, the
        # line search (the count of loops is the mode's, whichever kernels run them)
        (SolverSettings.paper(), 2, 2, "auto"),
        pytest.param(SolverSettings.paper(), 2, 2, "pallas-block-factor", marks=pytest.mark.slow),
    ],
)
def test_solver_lowers_for_a_gpu_in_few_kernels(settings, kernels, loops, variant):
    """Lowered for CUDA (the compile happens on the GPU; here the lowering catches errors),
    a batched and an unbatched solve with the kernels (and with ``kernel="auto"``, whose
    Triton kernels on a CUDA GPU are those of ``AUTO_ON_CUDA``, launch for launch) hold the
    Riccati sweeps as ``kernels`` Triton kernels and no loop over stages beyond the solve
    loop and (paper mode) the line search: the start's drift is a kernel or unrolled;
    ``kernel="xla"`` keeps XLA's loops on a GPU, and ``"auto"`` lowered for the CPU runs
    XLA's loops (these three checks, and the unbatched solve of ``"auto"``, in paper mode
    only: the choice is the same in either mode, and the accurate mode's lowering is the
    slowest). A small problem (N = 5) keeps the five lowerings cheap: the counts are the
    solver's, whatever the problem's sizes."""
    ocps = _random("small", 3)
    one = jax.tree.map(lambda a: a[0], ocps)
    settings = dataclasses.replace(settings, kernel=variant)
    batched = _cuda_text(jax.vmap(lambda o: solve(o, settings)), ocps)
    texts = [batched]
    if settings.mode == "paper" or variant != "auto":  # one problem alone: the same kernels
        texts.append(_cuda_text(lambda o: solve(o, settings), one))
    for text in texts:
        assert text.count("__gpu$xla.gpu.triton") == kernels
        assert text.count("stablehlo.while") == loops
    if variant != "auto" or settings.mode != "paper":
        return
    chosen = dataclasses.replace(settings, kernel=AUTO_ON_CUDA)
    chosen = _cuda_text(jax.vmap(lambda o: solve(o, chosen)), ocps)
    assert _triton_calls(batched) == _triton_calls(chosen)
    xla = dataclasses.replace(settings, kernel="xla")
    gpu_xla = _cuda_text(jax.vmap(lambda o: solve(o, xla)), ocps)
    assert "triton" not in gpu_xla and gpu_xla.count("stablehlo.while") > loops
    cpu_auto = jax.jit(jax.vmap(lambda o: solve(o, settings))).trace(ocps).lower().as_text()
    assert "triton" not in cpu_auto and cpu_auto.count("stablehlo.while") > loops


def _loop_body(text: str) -> str:
    """The body region of the first ``stablehlo.while`` of a lowered program (to the closing
    brace at the indentation of its ``} do {``)."""
    lines = text[text.index("stablehlo.while") :].splitlines()
    do = next(i for i, ln in enumerate(lines) if ln.strip() == "} do {")
    end = lines[do][: lines[do].index("}")] + "}"
    return "\n".join(lines[do + 1 : next(i for i in range(do + 1, len(lines)) if lines[i] == end)])


def test_a_batched_solve_for_a_gpu_takes_no_select_over_the_state(monkeypatch):
    """Lowered for a CUDA GPU, a vmapped accurate solve's loop takes every problem's
    iteration until the batch's last one finishes (driver._until_finished: a finished
    problem's iteration leaves it as it is), without vmap's select between each problem's old
    and new state: no select over the batch's (problems, stages, ...) arrays in the loop's
    body, where vmap's own rule puts one on each array of the state (checked by lowering with
    it). Run on the CPU (XLA's form, traced beside the kernels), the batch takes the same
    iterations and statuses as the CPU process's rule, and the same plans to 1e-12."""
    from rvdjax.solver import driver

    ocps = _random("small", 3)  # lowered twice: a small problem (N = 5) keeps it cheap
    fn = jax.vmap(lambda o: solve(o, SolverSettings()))

    def state_selects(text):  # selects of f64 arrays with a batch and a stage axis (3 x 5)
        return len(re.findall(r"stablehlo.select .*, tensor<3x5x[\dx]*f64>", _loop_body(text)))

    assert state_selects(_cuda_text(fn, ocps)) == 0
    with monkeypatch.context() as m:
        m.setattr(driver, "traces_cuda", lambda: False)  # vmap's own rule for the loop
        jax.clear_caches()  # solve's trace is cached
        assert state_selects(_cuda_text(fn, ocps)) >= 9  # u, x, nu, s, lam, mu, pi, su, g
    jax.clear_caches()
    problems = _random("small", 6)
    run = jax.vmap(lambda o: solve(o, SolverSettings(kernel="xla")))
    cpu = jax.jit(run)(problems)
    with tracing_for_cuda():
        gpu_loop = jax.jit(run)(problems)
    jax.clear_caches()  # no later test of this process reuses the GPU loop's trace on the CPU
    assert len(set(np.asarray(cpu.iterations).tolist())) > 1  # finished at different times
    np.testing.assert_array_equal(np.asarray(gpu_loop.iterations), np.asarray(cpu.iterations))
    np.testing.assert_array_equal(np.asarray(gpu_loop.status), np.asarray(cpu.status))
    assert _rel(cpu.u, gpu_loop.u) <= 1e-12


def test_a_cpu_process_traces_the_cpu_form_alone():
    """Without a GPU backend, ``kernel="auto"`` traces XLA's loops alone (no kernel traced for
    a program that can only run on the CPU); inside ``tracing_for_cuda`` the CUDA form is in
    the trace too, also for a solve whose CPU-only trace was cached before."""
    one = fastmpc3d_first_step(obstacles=True)
    settings = SolverSettings.paper()

    def fn(o):
        return solve(o, settings)

    assert "pallas_call" not in str(jax.make_jaxpr(fn)(one))
    with tracing_for_cuda():
        inside = str(jax.make_jaxpr(fn)(one))
    assert "pallas_call" in inside and "platform_index" in inside


def test_the_drift_is_a_loop_on_the_cpu_and_unrolled_for_a_gpu():
    """The start's drift (x_{t+1} = A_t x_t + B_t u_t + c_t) and a cold plan's: one loop over
    the stages lowered for the CPU, none lowered for a CUDA GPU (every trip of a loop there is
    several launches) and no matrix product there (a product of a matrix shared by a batch is
    a launch of its own; multiplies and sums fuse); the states those of the recursion written
    out in NumPy, and traced for both platforms the same on the CPU, bit for bit."""
    from rvdjax.solver.start import drift, drift_plan

    ocp = fastmpc3d_first_step(obstacles=True)
    u = jax.random.normal(jax.random.key(3), (ocp.N, ocp.nu)) * 0.01
    x, ref = np.asarray(ocp.x0), []
    for t in range(ocp.N):
        x = (
            np.asarray(ocp.A[t]) @ x
            + np.asarray(ocp.B[t]) @ np.asarray(u[t])
            + np.asarray(ocp.c[t])
        )
        ref.append(x)
    got = jax.jit(drift)(ocp, u)
    np.testing.assert_allclose(got, np.stack(ref), rtol=1e-12, atol=1e-12 * np.abs(ref).max())

    def cold(o):
        return drift_plan(o.A, o.x0, o.N, o.nu).x

    for fn, args in ((drift, (ocp, u)), (cold, (ocp,))):
        assert jax.jit(fn).trace(*args).lower().as_text().count("stablehlo.while") == 1
        with tracing_for_cuda():
            both = jax.jit(fn)(*args)
            cuda = jax.jit(fn).trace(*args).lower(lowering_platforms=("cuda",)).as_text()
        assert cuda.count("stablehlo.while") == 0
        assert "dot_general" not in cuda  # the products as multiplies and sums, which fuse
        np.testing.assert_array_equal(both, jax.jit(fn)(*args))


def test_the_drift_kernel_gives_the_recursion():
    """The start's drift as one kernel (pd_kernels.pd_drift with a form whose rows run in
    kernels, interpreted here): the states of x_{t+1} = A_t x_t + B_t u_t + c_t written out
    in NumPy, to 1e-12 relative, for one problem, a batch with a model each and a batch
    sharing its model and offset (read as a table of one and as scalars: no copy for every
    problem); lowered for a CUDA GPU, one Triton kernel and no loop."""
    from rvdjax.solver.primal_dual import pd_drift

    def recursion(A, B, c, u, x0):
        x, out = np.asarray(x0), []
        for t in range(A.shape[0]):
            x = np.asarray(A[t]) @ x + np.asarray(B[t]) @ np.asarray(u[t]) + np.asarray(c[t])
            out.append(x)
        return np.stack(out)

    ocp = fastmpc3d_first_step(obstacles=True)
    ocp = ocp._replace(c=0.01 * jax.random.normal(jax.random.key(4), ocp.c.shape))
    k = jax.random.split(jax.random.key(5), 3)
    us = 0.01 * jax.random.normal(k[0], (3, ocp.N, ocp.nu))
    x0s = ocp.x0 * (1.0 + 0.1 * jax.random.normal(k[1], (3, 1)))
    A_each = ocp.A * (1.0 + 1e-3 * jax.random.normal(k[2], (3, 1, 1, 1)))

    def drift(o, u):
        return pd_drift(o, u, "pallas-carried")

    def close(got, want):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())

    close(jax.jit(drift)(ocp, us[0]), recursion(ocp.A, ocp.B, ocp.c, us[0], ocp.x0))
    each = jax.vmap(lambda A, u, x0: drift(ocp._replace(A=A, x0=x0), u))
    want = [recursion(A_each[i], ocp.B, ocp.c, us[i], x0s[i]) for i in range(3)]
    close(jax.jit(each)(A_each, us, x0s), np.stack(want))
    shared = jax.vmap(lambda u, x0: drift(ocp._replace(x0=x0), u))
    calls = [
        [str(v.aval) for v in e.invars]
        for e in _eqns(jax.make_jaxpr(shared)(us, x0s).jaxpr)
        if e.primitive.name == "pallas_call"
    ]
    assert len(calls) == 1 and INDEX_OF_3 in calls[0]  # the model, a table of one
    assert f"float64[{ocp.N},6]" in calls[0]  # the offset, without a problem axis
    want = [recursion(ocp.A, ocp.B, ocp.c, us[i], x0s[i]) for i in range(3)]
    close(jax.jit(shared)(us, x0s), np.stack(want))
    with tracing_for_cuda():
        cuda = jax.jit(shared).trace(us, x0s).lower(lowering_platforms=("cuda",)).as_text()
    assert cuda.count("__gpu$xla.gpu.triton") == 1 and "stablehlo.while" not in cuda


def test_a_batch_smaller_than_a_tile_runs_in_one_tile_of_the_next_power_of_two():
    """Tiles of ``block`` lanes, padded by repeating the last problem; a batch smaller than a
    tile is one tile of the next power of two, so a problem alone is a tile of one: a solve
    of one QP traced for a CUDA GPU launches every kernel on one lane, with no padding to
    copy in and slice out around each launch (paper mode: the drift's kernel and the
    Riccati kernels, the two launchers every form uses, in the shortest trace)."""
    assert lanes.tile(1, 128) == (1, 1)
    assert lanes.tile(3, 8) == (4, 4)
    assert lanes.tile(8, 8) == (8, 8)
    assert lanes.tile(11, 8) == (8, 16)
    assert lanes.tile(65536, 128) == (128, 65536)
    ocp = fastmpc3d_first_step(obstacles=True)
    one = jax.tree.map(lambda a: a[None], ocp)
    with tracing_for_cuda():
        settings = SolverSettings.paper(kernel=AUTO_ON_CUDA)
        jaxpr = jax.make_jaxpr(jax.vmap(lambda o: solve(o, settings)))
        eqns = [e for e in _eqns(jaxpr(one).jaxpr) if e.primitive.name == "pallas_call"]
    names = {str(e.params["name"]) for e in eqns}
    assert "rvdjax_drift" in names and any("riccati" in n for n in names), names
    for e in eqns:
        assert tuple(e.params["grid_mapping"].grid) == (1,)
        assert all(v.aval.shape[-1] == 1 for v in e.outvars), e.params["name"]


def test_kernel_on_names_the_form_auto_runs_on_a_device():
    """What outputs print beside the device: "auto" is "pallas-carried" on a CUDA GPU
    and XLA's loops elsewhere; a chosen form is itself."""
    from types import SimpleNamespace

    from rvdjax.solver.platform import kernel_on

    def fake(platform, version):
        return SimpleNamespace(platform=platform, client=SimpleNamespace(platform_version=version))

    assert kernel_on(jax.devices("cpu")[0]) == "xla"
    assert kernel_on(fake("gpu", "PJRT C API\ncuda 13000")) == "pallas-carried"
    assert kernel_on(fake("gpu", "rocm 6.2")) == "xla"
    assert kernel_on(fake("gpu", "cuda 13000"), "xla") == "xla"
    assert kernel_on(jax.devices("cpu")[0], "pallas") == "pallas"


@pytest.mark.slow  # interpreted kernels in a closed loop: ~60 s
@pytest.mark.parametrize("form", [AUTO_ON_CUDA, "pallas-entries"])
def test_the_engine_flies_with_the_gpu_form_as_with_xla(monkeypatch, form):
    """The batch engine with the GPU form of the Newton step that carries the Newton system
    through a tick's iterations (the default, "pallas-carried") and with the one before it
    ("pallas-entries": the Newton blocks, the factorisation with the predictor's step, the
    row work between the solves, the corrector's step with its refinement and its update;
    both interpreted) flies thesis-vbar's first steps (a model per slot, rebuilt from the
    phase) as with XLA's loops: the same steps, run statuses and solver statuses, delta-v to
    1e-9; so too with the phase tables read by the kernels and the slots stored last, as on a
    GPU."""
    from rvdjax.bench import perturbed_states
    from rvdjax.loop.engine import EngineConfig, fly_batch, program, segment
    from rvdjax.scenarios import FlightOptions, get_scenario

    sc = get_scenario("thesis-vbar")
    options = FlightOptions(n_steps=6)
    flown = {}
    for kernel in ("xla", form):
        flight = sc.flight(options, settings=sc.settings(options.mode, kernel=kernel))
        x0s = perturbed_states(flight.x0, 3, rel=0.05)
        config = EngineConfig(slots=2, chunk=2, iterations=3)
        flown[kernel] = fly_batch(flight.loop, flight.params, x0s, config=config)
    # and as a GPU runs it: the kernels read the phase tables (traced for CUDA, so that the
    # family builds them), the slots stored last in the accelerator's engine settings
    asked = []
    monkeypatch.setattr(segment, "_slots_last", lambda c: asked.append(c) or True)
    program._build_one.cache_clear()
    try:
        with tracing_for_cuda():
            config = EngineConfig(slots=2, chunk=2, iterations=3, refresh="compacted", assign="any")
            flown["tables"] = fly_batch(flight.loop, flight.params, x0s, config=config)
    finally:
        program._build_one.cache_clear()
    assert asked  # built again, with the slots last
    xla = flown["xla"]
    for gpu in (flown[form], flown["tables"]):
        np.testing.assert_array_equal(np.asarray(gpu.steps), np.asarray(xla.steps))
        np.testing.assert_array_equal(np.asarray(gpu.status), np.asarray(xla.status))
        np.testing.assert_array_equal(np.asarray(gpu.status_counts), np.asarray(xla.status_counts))
        np.testing.assert_allclose(
            np.asarray(gpu.delta_v_m_s), np.asarray(xla.delta_v_m_s), rtol=1e-9
        )
