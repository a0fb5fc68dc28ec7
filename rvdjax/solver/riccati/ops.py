"""The recursion's operations as the solver calls them: one function per operation that
dispatches, by device and form, to XLA's loops or the kernels under ``vmap``, with the
derivatives of the dot form."""

from __future__ import annotations

import functools

import jax

from rvdjax.solver import lanes
from rvdjax.solver.platform import AUTO_ON_CUDA, cuda_or_default, traces_cuda
from rvdjax.solver.riccati.lane_rules import (
    _pallas_apply_refined_rule,
    _pallas_apply_rule,
    _pallas_factor_rule,
)
from rvdjax.solver.riccati.recursion import (
    _DOT,
    _ELEMENTWISE,
    ModelTable,
    NewtonStep,
    RiccatiFactor,
    _apply,
    _apply_refined,
    _factor,
)
from rvdjax.solver.riccati.xla_rules import (
    _factor_flags,
    _factor_solve,
    _packed_flags,
    _xla_apply_refined_rule,
    _xla_apply_rule,
    _xla_factor_rule,
    _xla_factor_solve_rule,
)
from rvdjax.solver.types import KERNELS, PALLAS_FORMS


def _packs(kernel: str) -> bool:
    """Whether the factor of ``kernel`` carries the kernels' storage of L and P (Lp, Pp):
    with the kernels, and with "auto" where a program may run on a CUDA GPU (both of
    :func:`cuda_or_default`'s branches give one structure)."""
    return kernel in PALLAS_FORMS or (kernel == "auto" and traces_cuda())


def _with_packed(op: str, out):
    """``out`` of ``op`` with its factor's Lp and Pp formed from L and P (batch first or
    unbatched: the matrices are the last two axes)."""
    if op == "factor_solve":
        return _with_packed("factor", out[0]), out[1]
    if op != "factor" or out.Lp is not None:
        return out
    return out._replace(Lp=lanes.tri_pack(out.L), Pp=lanes.tri_pack(out.P))


def _by_platform(kernel: str, xla, pallas, *args):
    """``xla(*args)`` or ``pallas(impl, *args)``: "xla" runs XLA's loops on every platform;
    a "pallas*" form runs the kernels (what each form runs:
    :data:`rvdjax.solver.types.PALLAS_FORMS`), compiled on a CUDA GPU and interpreted
    elsewhere (the tests); "unrolled" runs the kernels' algebra as XLA loops
    (:mod:`.unrolled`); "auto" runs :data:`AUTO_ON_CUDA` on a CUDA GPU and XLA's loops
    elsewhere, chosen when the program is lowered for its device.

    Why "auto" picks "pallas-carried" on a CUDA GPU: "pallas-block-factor" was the fastest
    form measured on a GPU (2026-11-27); in the programs compiled for an H100, counting each
    kernel's sweeps, the fused kernels move 12 % fewer bytes an accurate iteration than it
    (65 536 fastmpc-3d QPs) and the rows kernels 11-12 % fewer a tick of the batch engine
    than the fused kernels alone, where the bytes set the pace; with every operand entry by
    entry rather than in blocks (but the factorisation's model), the same bytes pass through
    almost no shared memory and barrier, and no kernel falls to 32 registers and kilobytes of
    spills ("pallas-entries"); with the next Newton system formed in the step's kernel, an
    iteration is four kernels and 6-9 % fewer bytes in a batch of QPs' solve loop, 2.4 % fewer
    a thesis-vbar tick, for a step kernel of 254 registers instead of 168 (ptxas for sm_90a;
    docs/benchmark.md; none of these timed on a GPU yet). On the CPU XLA's loops are the
    fastest form (the kernels are only interpreted there). The measurements are in
    docs/solver.md."""
    if kernel == "unrolled":
        return pallas("unrolled", *args)
    if kernel == "auto":
        return cuda_or_default(
            *args, cuda=functools.partial(pallas, (AUTO_ON_CUDA, False)), default=xla
        )
    if not kernel.startswith("pallas"):
        return xla(*args)
    return cuda_or_default(
        *args,
        cuda=functools.partial(pallas, (kernel, False)),
        default=functools.partial(pallas, (kernel, True)),
    )


# op: (unbatched XLA form, XLA vmap rule, kernels' vmap rule); a rule returns (out, flags)
_OPS = {
    "factor": (functools.partial(_factor, ops=_ELEMENTWISE), _xla_factor_rule, _pallas_factor_rule),
    "apply": (functools.partial(_apply, ops=_ELEMENTWISE), _xla_apply_rule, _pallas_apply_rule),
    "factor_solve": (
        functools.partial(_factor_solve, ops=_ELEMENTWISE),
        _xla_factor_solve_rule,
        _pallas_factor_rule,
    ),
    "apply_refined": (
        functools.partial(_apply_refined, ops=_ELEMENTWISE),
        _xla_apply_refined_rule,
        _pallas_apply_refined_rule,
    ),
}


@functools.cache
def _batched(op: str, kernel: str, tabled: bool = False):
    """The recursion ``op`` as a custom_vmap function dispatching on ``kernel``: unbatched,
    the kernels run a batch of one; under vmap, the rules above (the batch dimension of each
    output is the same whichever form runs). ``tabled``: the last argument is a
    :class:`~rvdjax.solver.riccati.recursion.ModelTable`, which the kernels' rules read where it is
    shared and its index batched, and everything else ignores."""
    xla_fn, xla_rule, pallas_rule = _OPS[op]

    def flags(in_batched):
        fb = _factor_flags(in_batched)
        fb = _packed_flags(fb) if _packs(kernel) else fb
        if op == "factor":
            return fb
        if op in ("apply", "apply_refined"):
            return NewtonStep(True, True, True)
        return fb, NewtonStep(True, True, True)

    def packed(out):  # XLA's forms give the factor the kernels' storage where they do
        return _with_packed(op, out) if _packs(kernel) else out

    def one(impl, *args):
        batched = jax.tree.map(lambda _: True, args)
        out, _ = pallas_rule(impl, 1, batched, *jax.tree.map(lambda a: a[None], args))
        return jax.tree.map(lambda a: a[0], out)

    @jax.custom_batching.custom_vmap
    def fn(*args):
        if tabled:
            args = args[:-1]
        return _by_platform(kernel, lambda *a: packed(xla_fn(*a)), one, *args)

    @fn.def_vmap
    def rule(axis_size, in_batched, *args):
        table = None
        if tabled:
            table, tb = args[-1], in_batched[-1]
            args, in_batched = args[:-1], in_batched[:-1]
            if tb.M or not tb.index:  # a table per problem, or one model for all: no use
                table = None
        out = _by_platform(
            kernel,
            lambda *a: packed(xla_rule(axis_size, in_batched, *a)[0]),
            lambda i, *a: pallas_rule(i, axis_size, in_batched, *a, table=table)[0],
            *args,
        )
        return out, flags(in_batched)

    return fn


def _dot_derivative(fn, op: str = ""):
    """A custom_jvp rule: the derivative of ``fn``'s dot form (``kernel`` is not
    differentiated, and a :class:`~rvdjax.solver.riccati.recursion.ModelTable`, the last primal,
    only repeats A and B), the factor of ``op`` with the kernels' storage where ``kernel``'s has
    it."""

    def jvp(kernel, primals, tangents):
        primals, tangents = primals[:-1], tangents[:-1]

        def dot(*a):
            out = fn(*a, _DOT)
            return _with_packed(op, out) if _packs(kernel) else out

        return jax.jvp(dot, primals, tangents)

    return jvp


def _run(op: str, kernel: str, args, table):
    if table is None:
        return _batched(op, kernel)(*args)
    return _batched(op, kernel, True)(*args, ModelTable(*table))


def _check_kernel(kernel):
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def riccati_factor(A, B, Phi_u, Phi_x, kernel: str = "auto", table=None) -> RiccatiFactor:
    """Backward Riccati sweep over the KKT matrix (paper 000 Eqs. 24-26 by stage elimination).

    The cost-to-go of x_t is 1/2 dx^T P_t dx + p_t^T dx with P_N = Phi_x[N-1] and
    P_t = Phi_x[t-1] + A^T P A - A^T P B H^-1 B^T P A, H = Phi_u + B^T P B, evaluated in the
    equal Joseph form Phi_x[t-1] + (A + B K)^T P (A + B K) + K^T Phi_u K with the gain
    K = -H^-1 B^T P A refined once against H (the reasons are in the code).

    Args:
        A: (N, nx, nx), B: (N, nx, nu) stage dynamics.
        Phi_u: (N, nu, nu), Phi_x: (N, nx, nx) Hessian blocks (Phi_u positive definite,
            Phi_x positive semidefinite).
        kernel: "auto" (:data:`AUTO_ON_CUDA` on a CUDA GPU, else XLA's loops), "xla"
            (XLA's loops), a form of :data:`rvdjax.solver.types.PALLAS_FORMS` (the kernels of
            :mod:`rvdjax.solver.lanes`; compiled on a CUDA GPU, interpreted elsewhere) or
            "unrolled" (their algebra as XLA loops, :mod:`rvdjax.solver.unrolled`).
        table: a :class:`~rvdjax.solver.riccati.recursion.ModelTable` whose entry is [B, A],
            or None: under ``vmap`` with the table shared and its index batched, the kernels
            read the model from it.
    """
    _check_kernel(kernel)
    return _run("factor", kernel, (A, B, Phi_u, Phi_x), table)


riccati_factor.defjvp(_dot_derivative(_factor, "factor"))


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def riccati_apply(f: RiccatiFactor, g_u, g_x, rp, kernel: str = "auto", table=None) -> NewtonStep:
    """Solve the factorised KKT system for one right-hand side (g_u, g_x, rp).

    A backward sweep for the affine terms (p_t, k_t) and a forward sweep for the step:
    du_t = K_t dx_t + k_t, dx_{t+1} = A dx_t + B du_t - rp_t, nu+_t = -(P_{t+1} dx_{t+1} +
    p_{t+1}). ``kernel`` and ``table`` as :func:`riccati_factor`.
    """
    _check_kernel(kernel)
    return _run("apply", kernel, (f, g_u, g_x, rp), table)


riccati_apply.defjvp(_dot_derivative(_apply))


@functools.partial(jax.custom_jvp, nondiff_argnums=(7,))
def riccati_factor_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, kernel: str = "auto", table=None):
    """:func:`riccati_factor` and :func:`riccati_apply` of one right-hand side together:
    (RiccatiFactor, NewtonStep). With the kernels, the factorisation and the step are two
    kernels (:class:`rvdjax.solver.lanes.KernelConfig`, ``fused``). ``kernel`` and ``table``
    as :func:`riccati_factor`."""
    _check_kernel(kernel)
    return _run("factor_solve", kernel, (A, B, Phi_u, Phi_x, g_u, g_x, rp), table)


riccati_factor_solve.defjvp(_dot_derivative(_factor_solve, "factor_solve"))


# the forms whose kernels also refine a step (riccati_apply_refined); the others refine with a
# residual formed by XLA and one more solve (rvdjax.solver.kkt.kkt_solve_refined)
REFINED_IN_KERNEL = tuple(k for k, form in PALLAS_FORMS.items() if form.fused)
# the forms whose accurate-mode iteration also runs its row work as kernels, before the first
# solve, between the two and after them (rvdjax.solver.rows_kernel), and of those the one
# whose row kernels load and store a stage's blocks (the other reads them entry by entry)
ROWS_IN_KERNEL = tuple(k for k, form in PALLAS_FORMS.items() if form.rows)
ROWS_BLOCK_IO = tuple(k for k, form in PALLAS_FORMS.items() if form.rows_block_io)
# the forms whose solves carry the next Newton system from one iteration to the next
# (rvdjax.solver.pd_algebra.PDState.system)
SYSTEM_CARRIED = tuple(k for k, form in PALLAS_FORMS.items() if form.rows and form.carried)


@functools.partial(jax.custom_jvp, nondiff_argnums=(6,))
def riccati_apply_refined(
    f: RiccatiFactor, Phi_u, Phi_x, g_u, g_x, rp, kernel: str = "pallas-block-fused", table=None
) -> NewtonStep:
    """:func:`riccati_apply` and one step of iterative refinement against the KKT matrix of
    ``f`` and the Hessian blocks Phi_u, Phi_x
    (:func:`~rvdjax.solver.riccati.recursion.newton_residual`, then one more solve): with a kernel
    of :data:`REFINED_IN_KERNEL`, one kernel that forms the residual inside its sweeps. ``kernel``
    and ``table`` as :func:`riccati_factor`."""
    _check_kernel(kernel)
    return _run("apply_refined", kernel, (f, Phi_u, Phi_x, g_u, g_x, rp), table)


riccati_apply_refined.defjvp(_dot_derivative(_apply_refined))


def riccati_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, kernel: str = "auto") -> NewtonStep:
    """Solve the stage-structured KKT system: :func:`riccati_factor` then :func:`riccati_apply`.

    Args:
        A: (N, nx, nx), B: (N, nx, nu) stage dynamics.
        Phi_u: (N, nu, nu), Phi_x: (N, nx, nx) Hessian blocks.
        g_u: (N, nu), g_x: (N, nx) gradient blocks.
        rp: (N, nx) dynamics residual x_{t+1} - A_t x_t - B_t u_t - c_t.
        kernel: as :func:`riccati_factor`.

    Returns:
        The :class:`~rvdjax.solver.riccati.recursion.NewtonStep`. Non-finite entries signal a failed
        factorisation.
    """
    return riccati_factor_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, kernel)[1]
