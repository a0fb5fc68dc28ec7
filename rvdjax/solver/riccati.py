"""The structured Newton step: the Riccati recursion on the KKT system of
:mod:`rvdjax.solver.kkt`, and the batching rules that run it on XLA's loops or the GPU kernels.

:func:`riccati_solve` eliminates the system stage by stage (a discrete Riccati recursion on
the KKT system, equivalent to the block Cholesky factorisation of Y = C Phi^-1 C^T of
paper 000 Eqs. 24-26): O(N (nx + nu)^3) work, `lax.scan` over stages, no dense matrix. Under
``vmap``, custom batching rules choose the layout (batch axis last or first) or the kernels of
:mod:`rvdjax.solver.lanes`; derivatives are those of the dot form. Notation and sign
convention as in :mod:`rvdjax.solver.kkt`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg
from jax import lax

from rvdjax.solver import lanes, unrolled
from rvdjax.solver import stagewise as sw
from rvdjax.solver.barrier import dual_residual
from rvdjax.solver.stagewise import shift as _shift
from rvdjax.solver.types import (  # the Newton step's forms, checked by SolverSettings
    KERNELS,
    PALLAS_FORMS,
)

__all__ = [
    "ModelTable",
    "NewtonStep",
    "SymStored",
    "RiccatiFactor",
    "riccati_factor",
    "riccati_apply",
    "riccati_solve",
    "KERNELS",
    "kernel_on",
    "riccati_factor_solve",
    "riccati_apply_refined",
    "newton_residual",
    "REFINED_IN_KERNEL",
    "tracing_for_cuda",
    "traces_cuda",
]


class NewtonStep(NamedTuple):
    """Solution of one KKT system.

    Attributes:
        du: (N, nu) input step.
        dx: (N, nx) state step (dx[t] is the step of x_{t+1}).
        nu: (N, nx) new dynamics multipliers (nu + dnu).
    """

    du: jnp.ndarray
    dx: jnp.ndarray
    nu: jnp.ndarray


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, 0, 1))


class RiccatiFactor(NamedTuple):
    """Stage-wise factorisation of the KKT matrix (independent of the right-hand side).

    Attributes:
        M: (N, nx, nu + nx) the stage dynamics [B_t, A_t].
        L: (N, nu, nu) Cholesky factor of the reduced Hessian Phi_u + B^T P_{t+1} B.
        K: (N, nu, nx) feedback gain, du_t = K_t dx_t + k_t. No other product of the
            factorisation (B^T P A) is stored (:func:`_apply`). The GPU kernels store only L
            and P (``Lp``, ``Pp``) and solve without the gain; with their forms K is formed
            from L and P, and is dead code where nothing else reads it.
        P: (N, nx, nx) cost-to-go Hessian P_{t+1} of x_{t+1}.
        Lp: (N, nu (nu + 1) / 2) L's lower triangle and ``Pp`` (N, nx (nx + 1) / 2) P's, as
            the GPU kernels store them (:func:`rvdjax.solver.lanes.pack`), or None (both or
            neither): present with the kernels' forms (and "auto" where a program may run
            on a CUDA GPU), so that a factorisation goes from the factorisation's kernel to
            the solves' in that storage. XLA does not fold the copy of the triangles into
            the matrices and back between two kernels; L and P, for every other use, are
            dead code there.
    """

    M: jnp.ndarray
    L: jnp.ndarray
    K: jnp.ndarray
    P: jnp.ndarray
    Lp: Any = None
    Pp: Any = None


class ModelTable(NamedTuple):
    """K models' stage dynamics (and, optionally, rows) and the one a problem runs:
    ``M[index]`` is the problem's [B_t, A_t]. The batch engine's three-phase family flies one
    model per phase: under ``vmap``, with the tables shared and the index batched, the GPU
    kernels read each problem's stages from the tables instead of from a copy of every
    problem's (the Riccati kernels [B, A], 13 KB a thesis-vbar slot read in every sweep; the
    row kernels of :mod:`rvdjax.solver.rows_kernel` the input rows and the soft rows' mask
    and penalty: docs/benchmark.md). Every other form ignores them: the OCP's arrays are
    passed too, and must equal the tables' entries (the caller's promise, not checked).

    Attributes:
        M: (K, N, nx, nu + nx) the stages' [B_t, A_t] of each model.
        index: () int, the problem's model.
        Fu: (K, N, mu, nu) the input rows before the problem's mask neutralises them (the
            kernels zero the rows whose mask is off, as ``barrier.rows_of`` does), or None.
        x_mask: (K, N, mx) the soft rows' mask, and ``rho`` (K, N, mx) their penalty
            neutralised (1) where the mask is off, or None (both or neither, with ``Fu``).
        Q: (K, N, nx, nx) and ``R`` (K, N, nu, nu) the cost blocks, or None (both or
            neither): with the rows' tables, the kernel that forms the Newton blocks reads
            them too.
    """

    M: Any
    index: Any
    Fu: Any = None
    x_mask: Any = None
    rho: Any = None
    Q: Any = None
    R: Any = None


class SymStored(NamedTuple):
    """A stage-wise symmetric Hessian block and its lower triangle, as the GPU kernels store
    it: the blocks' kernel (:func:`rvdjax.solver.rows_kernel.pd_blocks`) writes Phi_u and
    Phi_x as their lower triangles (:func:`rvdjax.solver.lanes.tri_pack`: 6 and 21 entries a
    stage instead of 9 and 36), which the Riccati kernels read as they are. XLA does not fold
    a copy of the triangles into whole matrices and back between two kernels, so the
    triangles go beside the whole matrices, which every other use reads (the XLA forms, the
    derivatives) and which are dead code where none does. Every function here that takes
    Phi_u or Phi_x takes either an array or this.

    Attributes:
        whole: (N, n, n) the blocks.
        lower: (N, n (n + 1) / 2) their lower triangles, row by row.
    """

    whole: Any
    lower: Any


def whole(a):
    """The matrices of a Hessian block passed as an array or as :class:`SymStored`."""
    return a.whole if isinstance(a, SymStored) else a


def _lower(a, axis: int):
    """The lower triangles of a Hessian block (:class:`SymStored`'s, or formed from the
    matrices at ``axis`` and the next)."""
    return a.lower if isinstance(a, SymStored) else lanes.tri_pack(a, axis)


def _small_chol(H):
    """Cholesky of a small SPD matrix written out element by element
    (:func:`rvdjax.solver.lanes.chol`).

    Under ``vmap`` each entry becomes one vector operation over the batch; XLA's batched
    LAPACK call costs more than the arithmetic at these sizes. NaN if H is not SPD. Indexes
    the two leading axes only, so H may carry trailing batch axes.
    """
    n = H.shape[0]
    L = lanes.chol([[H[i, j] for j in range(n)] for i in range(n)])
    zero = jnp.zeros_like(H[0, 0])
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(n)]) for i in range(n)])


def _chol_solve(L, b):
    """Solve (L L^T) X = b for small lower-triangular L; b of shape (n,) or (n, k) (and the
    same trailing batch axes as L, if any)."""
    n = L.shape[0]
    return jnp.stack(lanes.chol_solve([[L[i, j] for j in range(n)] for i in range(n)], list(b)))


# --------------------------------------------------------------- products, two formulations
#
# The recursion below is written once over four small products. ``_DOT`` uses matrix
# products (``dot_general``: what XLA handles best for batches kept first and large).
# ``_ELEMENTWISE`` writes each product as a broadcast multiply and a sum over the contracted
# axis, indexing leading axes only, so the same code runs on one problem or on arrays with a
# trailing batch axis, where every operation vectorises over the batch. Per problem (N = 30,
# nx = 6, nu = 3, one factorisation and two solves): sweeps/kkt_layouts.py, docs/benchmark.md.


class _Products(NamedTuple):
    mm: Any  # X @ Y
    mtm: Any  # X^T @ Y
    mv: Any  # X @ v
    mtv: Any  # X^T @ v


_DOT = _Products(
    mm=lambda X, Y: X @ Y,
    mtm=lambda X, Y: X.T @ Y,
    mv=lambda X, v: X @ v,
    mtv=lambda X, v: X.T @ v,
)
_ELEMENTWISE = _Products(
    mm=lambda X, Y: jnp.sum(X[:, :, None] * Y[None, :, :], axis=1),
    mtm=lambda X, Y: jnp.sum(X[:, :, None] * Y[:, None, :], axis=0),
    mv=lambda X, v: jnp.sum(X * v[None, :], axis=1),
    mtv=lambda X, v: jnp.sum(X * v[:, None], axis=0),
)


def _factor(A, B, Phi_u, Phi_x, ops: _Products) -> RiccatiFactor:
    Phi_u, Phi_x = whole(Phi_u), whole(Phi_x)
    nu = B.shape[2]
    batch = jnp.broadcast_shapes(A.shape[3:], B.shape[3:])
    A = jnp.broadcast_to(A, A.shape[:3] + batch)
    B = jnp.broadcast_to(B, B.shape[:3] + batch)
    M = jnp.concatenate([B, A], axis=2)

    def backward(P, stage):
        M_t, Phu, Phx = stage
        B_t, A_t = M_t[:, :nu], M_t[:, nu:]
        PM = ops.mm(P, M_t)  # [PB, PA]
        BPM = ops.mtm(B_t, PM)  # [B'PB, B'PA]
        H = Phu + _sym(BPM[:, :nu])
        L = _small_chol(H)
        BPA = BPM[:, nu:]
        K = -_chol_solve(L, BPA)
        # Late in a solve the barrier weights reach 1e9-1e12 and H's condition number
        # follows. The two substitutions then move the last bits of their inputs into K's
        # leading digits, and XLA may evaluate the same substitution with different
        # FMA contractions in different consumers: with its loops compiled whole, K was
        # 1e-9 away (backward error) from the H it came from and the factorisation
        # broke down. One refinement step against H restores K to rounding level.
        K = K - _chol_solve(L, ops.mm(H, K) + BPA)
        # Joseph form (A + BK)' P (A + BK) + K' Phu K: a sum of PSD terms, so P stays PSD
        # whatever K's rounding, and an error in K enters P at second order only (the
        # subtractive form A'PA - A'PB H^-1 B'PA takes it at first order).
        PAcl = PM[:, nu:] + ops.mm(PM[:, :nu], K)
        Acl = A_t + ops.mm(B_t, K)
        P_new = Phx + _sym(ops.mtm(Acl, PAcl)) + _sym(ops.mtm(K, ops.mm(Phu, K)))
        return P_new, (L, K, P)

    _, (L, K, P) = lax.scan(backward, Phi_x[-1], (M, Phi_u, _shift(Phi_x)), reverse=True)
    return RiccatiFactor(M, L, K, P)


def _apply(f: RiccatiFactor, g_u, g_x, rp, ops: _Products) -> NewtonStep:
    nu = f.L.shape[1]

    # p_t = g_x + A^T q + (B^T P A)^T k with k = -H^-1 v, v = g_u + B^T q, q = p - P r; as
    # K = -H^-1 B^T P A, (B^T P A)^T k = K^T v: the gain the forward sweep reads anyway
    # stands for B^T P A, which is then not stored. (The GPU kernels, whose sweeps read the
    # factorisation from device memory, form the same step from L and P alone:
    # rvdjax.solver.lanes.stage._backward_rhs_stored, _forward_solved; docs/solver.md.)
    def backward(p, stage):
        M_t, L, K, P, gu, r, gx = stage
        Mp = ops.mtv(M_t, p - ops.mv(P, r))
        v = gu + Mp[:nu]
        k = -_chol_solve(L, v)
        return gx + Mp[nu:] + ops.mtv(K, v), (k, p)

    stages = (f.M, f.L, f.K, f.P, g_u, rp, _shift(g_x))
    _, (k, p_next) = lax.scan(backward, g_x[-1], stages, reverse=True)

    def forward(dx_t, stage):
        M_t, K_t, k_t, r, P, p = stage
        du = ops.mv(K_t, dx_t) + k_t
        dx_next = ops.mv(M_t, jnp.concatenate([du, dx_t])) - r
        return dx_next, (du, dx_next, -(ops.mv(P, dx_next) + p))

    _, (du, dx, nu_new) = lax.scan(forward, jnp.zeros_like(rp[0]), (f.M, f.K, k, rp, f.P, p_next))
    return NewtonStep(du, dx, nu_new)


class _Model(NamedTuple):
    A: Any
    B: Any


def newton_residual(A, B, Phi_u, Phi_x, g_u, g_x, rp, step: NewtonStep):
    """K z + (g, rp) for z = (du, dx, nu): the residual of the stage-structured Newton system
    (the rows of :func:`rvdjax.solver.kkt.dense_solve`'s matrix, applied stage by stage)."""
    Phi_u, Phi_x = whole(Phi_u), whole(Phi_x)
    r_u, r_x = dual_residual(
        _Model(A, B), sw.mv(Phi_u, step.du) + g_u, sw.mv(Phi_x, step.dx) + g_x, step.nu
    )
    r_p = step.dx - sw.mv(B, step.du) - sw.mv(A, _shift(step.dx)) + rp
    return r_u, r_x, r_p


def _apply_refined(f: RiccatiFactor, Phi_u, Phi_x, g_u, g_x, rp, ops: _Products) -> NewtonStep:
    """:func:`_apply`, then one step of iterative refinement: the XLA form of the kernel
    :func:`rvdjax.solver.lanes.apply_refined`."""
    nu = f.L.shape[1]
    A, B = f.M[:, :, nu:], f.M[:, :, :nu]
    step = _apply(f, g_u, g_x, rp, ops)
    d = _apply(f, *newton_residual(A, B, Phi_u, Phi_x, g_u, g_x, rp, step), ops)
    return NewtonStep(*(a + b for a, b in zip(step, d, strict=True)))


# ------------------------------------------------------------- batching and differentiation
#
# Unbatched, the elementwise form runs (fewer, fused operations on 6x6 blocks). Under
# ``vmap`` (custom_vmap) a batch of at most BATCH_LAST_MAX problems moves its batch axis last
# and runs the elementwise form; a larger batch runs the elementwise form with the batch first
# (an ordinary vmap): past a few hundred problems the batch-last working set leaves the cache.
# With XLA's loops compiled whole (rvdjax.xla_options) the elementwise form beats the dot form
# at every batch size measured (sweeps/kkt_layouts.py, docs/benchmark.md). Derivatives
# (custom_jvp) are those of the dot form: custom_vmap has no reverse-mode rule, and both
# forms compute the same function.

BATCH_LAST_MAX = 512


def _full(axis_size, a, batched):
    """``a`` with the batch axis first, broadcast if it had none."""
    return a if batched else jnp.broadcast_to(a, (axis_size, *a.shape))


def _to_last(a, batched=True):
    if not batched:
        return a[..., None]  # broadcasts against the batch inside the elementwise form
    return jnp.moveaxis(a, 0, -1)


def _to_first(a):
    return jnp.moveaxis(a, -1, 0)


def _first_vmap(fn, in_batched, args, out_batched):
    """The elementwise form under an ordinary ``vmap`` (batches above BATCH_LAST_MAX)."""
    axes = jax.tree.map(lambda b: 0 if b else None, in_batched)
    return jax.vmap(lambda *a: fn(*a, _ELEMENTWISE), in_axes=axes)(*args), out_batched


def _xla_factor_rule(axis_size, in_batched, A, B, Phi_u, Phi_x):
    if axis_size > BATCH_LAST_MAX:
        flags = _factor_flags(in_batched)
        f, _ = _first_vmap(_factor, in_batched, (A, B, Phi_u, Phi_x), flags)
        if not flags.M:  # a shared model stays shared (the vmapped copy is dead code)
            f = f._replace(M=jnp.concatenate([B, A], axis=-1))
        return f, flags
    bA, bB, bPu, bPx = in_batched
    f = _factor(
        _to_last(A, bA),
        _to_last(B, bB),
        _to_last(_full(axis_size, whole(Phi_u), whole(bPu))),
        _to_last(_full(axis_size, whole(Phi_x), whole(bPx))),
        _ELEMENTWISE,
    )
    m_batched = bool(bA or bB)
    M = _to_first(f.M) if m_batched else f.M[..., 0]
    out = RiccatiFactor(M, *(_to_first(a) for a in f[1:4]))
    return out, RiccatiFactor(m_batched, True, True, True)


def _xla_apply_rule(axis_size, in_batched, f, g_u, g_x, rp):
    if axis_size > BATCH_LAST_MAX:
        return _first_vmap(_apply, in_batched, (f, g_u, g_x, rp), NewtonStep(True, True, True))
    fb, bu, bx, br = in_batched
    # every operand but M carries the batch
    f = RiccatiFactor(
        _to_last(f.M, fb.M),
        *(_to_last(_full(axis_size, a, b)) for a, b in zip(f[1:4], fb[1:4], strict=True)),
    )
    g_u, g_x, rp = (_to_last(_full(axis_size, a, b)) for a, b in ((g_u, bu), (g_x, bx), (rp, br)))
    out = _apply(f, g_u, g_x, rp, _ELEMENTWISE)
    return NewtonStep(*(_to_first(a) for a in out)), NewtonStep(True, True, True)


# ------------------------------------------------------------------- the GPU kernels' layout
#
# The kernels of :mod:`rvdjax.solver.lanes` take the batch as the minor axis. Under ``vmap``
# the operands arrive batch first; they are moved last for the kernel and the results moved
# back. Between a factorisation and its solves the two moves cancel (XLA folds a transpose of
# a transpose), so the factorisation stays in the kernels' layout on the device.


def _lane_ops(impl):
    """(factor, factor_solve, apply, apply_refined) of the batch-last forms: ``impl``
    "unrolled" (XLA's loops, :mod:`rvdjax.solver.unrolled`), or (kernel, interpret): the
    Pallas kernels of a "pallas*" kernel name, interpreted or not (each also takes a model
    table and an ``index``: :func:`rvdjax.solver.lanes.factor`). The variant is in the name
    (static in SolverSettings, so a program traced with one is never reused for another)."""
    if impl == "unrolled":
        return unrolled.factor, unrolled.factor_solve, unrolled.apply, None
    kernel, interpret = impl
    form = PALLAS_FORMS[kernel]
    cfg = dataclasses.replace(
        lanes.default_config(),
        interpret=interpret,
        block_io=form.block_io,
        solve_block_io=form.solve_block_io,
        fused=form.fused,
        model_blocks_only=form.model_blocks_only,
    )
    factor, apply, apply_refined = (
        functools.partial(f, cfg=cfg) for f in (lanes.factor, lanes.apply, lanes.apply_refined)
    )
    if cfg.fused:
        return factor, functools.partial(lanes.factor_solve, cfg=cfg), apply, apply_refined

    def factor_solve(M, Phi_u, Phi_x, g_u, g_x, rp, **at):
        f = factor(M, Phi_u, Phi_x, **at)
        return f, apply(M, *f, g_u, g_x, rp, **at)

    return factor, factor_solve, apply, apply_refined


def _model_M(axis_size, A, B, bA, bB, batched: bool):
    """[B, A] with the batch first when ``batched`` (else shared)."""
    if batched:
        A, B = _full(axis_size, A, bA), _full(axis_size, B, bB)
    return jnp.concatenate([B, A], axis=-1)


def _lane_model(impl, M, batched: bool, table):
    """(model, index) for the kernels: the batch-last [B, A] of each problem (or the shared
    one) and None, or the shared ``table`` (:class:`ModelTable`, its index batched) and the
    problems' indices where the model is per problem and the kernels read tables (every
    "pallas*" form; the "unrolled" loops take the copy)."""
    if table is not None and batched and impl != "unrolled":
        return table.M, table.index
    return (_to_last(M) if batched else M), None


def _pallas_factor_rule(impl, axis_size, in_batched, A, B, Phi_u, Phi_x, *rhs, table=None):
    """The factorisation by the kernels (with a right-hand side ``rhs`` = g_u, g_x, rp: and
    its first step, ``(factor, step)``), outputs batch first; flags as the XLA rule's. With
    a ``table`` the kernels read the model from it (the factor's M is then the copy, for
    forms that use it)."""
    bA, bB, bPu, bPx = in_batched[:4]
    flags = _factor_flags(in_batched)
    M = _model_M(axis_size, A, B, bA, bB, flags.M)
    lane_M, index = _lane_model(impl, M, flags.M, table)
    mats = _lane_blocks(impl, axis_size, (Phi_u, bPu), (Phi_x, bPx))
    factor, factor_solve, _, _ = _lane_ops(impl)
    at = {} if index is None else {"index": index}
    if impl != "unrolled":
        flags = _packed_flags(flags)
    if not rhs:
        return _lane_factor(impl, M, factor(lane_M, *mats, **at)), flags
    vecs = [_to_last(_full(axis_size, a, b)) for a, b in zip(rhs, in_batched[4:], strict=True)]
    f, s = factor_solve(lane_M, *mats, *vecs, **at)
    out = (_lane_factor(impl, M, f), NewtonStep(*(_to_first(a) for a in s)))
    return out, (flags, NewtonStep(True, True, True))


def _lane_factor(impl, M, f) -> RiccatiFactor:
    """The factor, batch first, of a batch-last factorisation: the kernels' (L and P packed,
    :func:`rvdjax.solver.lanes.pack`: both forms kept, and the gain K formed from them, which
    no kernel reads: dead code unless another use reads it) or the unrolled loops'."""
    if impl == "unrolled":
        return RiccatiFactor(M, *(_to_first(a) for a in f))
    L, P = (_to_first(a) for a in lanes.unpack(*f))
    return RiccatiFactor(M, L, _gain(M, L, P), P, *(_to_first(a) for a in f))


def _gain(M, L, P):
    """K = -H^-1 B^T P A of each stage, batch first, from [B, A] (batch first or shared), the
    Cholesky factor L of H and P: one solve, where XLA's factorisation refines its gain once
    against H (riccati._factor), so the two agree to H's conditioning times rounding."""
    nu = L.shape[-1]
    BPA = jnp.einsum("...ji,...jk,...kl->...il", M[..., :nu], P, M[..., nu:])
    return -jax.scipy.linalg.cho_solve((L, True), BPA)


def _lane_factor_mats(impl, axis_size, f: RiccatiFactor, fb: RiccatiFactor):
    """The batch-last (L, P) a solve's kernel reads (packed, from the factor's storage
    for the kernels or from L and P), or the unrolled loops' (L, K, P, whole)."""
    fields = list(zip(f[1:4], fb[1:4], strict=True))
    if impl != "unrolled":
        if f.Lp is None:
            fields = [(lanes.tri_pack(f.L), fb.L), (lanes.tri_pack(f.P), fb.P)]
        else:
            fields = [(f.Lp, fb.Lp), (f.Pp, fb.Pp)]
    return [_to_last(_full(axis_size, a, b)) for a, b in fields]


def _lane_blocks(impl, axis_size, *blocks):
    """The batch-last Hessian blocks a kernel reads, each given as (block, batched): the
    lower triangles for the Pallas kernels (:class:`SymStored`'s, or packed from the
    matrices), the matrices for the unrolled loops."""
    if impl == "unrolled":
        return [_to_last(_full(axis_size, whole(a), whole(b))) for a, b in blocks]
    return [_to_last(_full(axis_size, _lower(a, -2), _lower_flag(b))) for a, b in blocks]


def _lower_flag(b):
    """The batch flag of :func:`_lower`'s triangles (a custom_vmap rule's flags come in the
    arguments' structure)."""
    return b.lower if isinstance(b, SymStored) else b


def _pallas_apply_rule(impl, axis_size, in_batched, f, g_u, g_x, rp, table=None):
    fb, bu, bx, br = in_batched
    mats = _lane_factor_mats(impl, axis_size, f, fb)
    vecs = [_to_last(_full(axis_size, a, b)) for a, b in ((g_u, bu), (g_x, bx), (rp, br))]
    lane_M, index = _lane_model(impl, f.M, fb.M, table)
    at = {} if index is None else {"index": index}
    s = _lane_ops(impl)[2](lane_M, *mats, *vecs, **at)
    return NewtonStep(*(_to_first(a) for a in s)), NewtonStep(True, True, True)


def _pallas_apply_refined_rule(
    impl, axis_size, in_batched, f, Phi_u, Phi_x, g_u, g_x, rp, table=None
):
    if impl == "unrolled":  # no kernel of its own: the two solves and the residual
        return _xla_apply_refined_rule(axis_size, in_batched, f, Phi_u, Phi_x, g_u, g_x, rp)
    fb, bPu, bPx, bu, bx, br = in_batched
    mats = _lane_factor_mats(impl, axis_size, f, fb)
    mats += _lane_blocks(impl, axis_size, (Phi_u, bPu), (Phi_x, bPx))
    vecs = [_to_last(_full(axis_size, a, b)) for a, b in ((g_u, bu), (g_x, bx), (rp, br))]
    lane_M, index = _lane_model(impl, f.M, fb.M, table)
    at = {} if index is None else {"index": index}
    s = _lane_ops(impl)[3](lane_M, *mats, *vecs, **at)
    return NewtonStep(*(_to_first(a) for a in s)), NewtonStep(True, True, True)


def _xla_apply_refined_rule(axis_size, in_batched, *args):
    out, _ = _first_vmap(_apply_refined, in_batched, args, NewtonStep(True, True, True))
    return out, NewtonStep(True, True, True)


def _xla_factor_solve_rule(axis_size, in_batched, A, B, Phi_u, Phi_x, g_u, g_x, rp):
    f, fb = _xla_factor_rule(axis_size, in_batched[:4], A, B, Phi_u, Phi_x)
    s, sb = _xla_apply_rule(axis_size, (fb, *in_batched[4:]), f, g_u, g_x, rp)
    return (f, s), (fb, sb)


def _factor_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, ops):
    f = _factor(A, B, Phi_u, Phi_x, ops)
    return f, _apply(f, g_u, g_x, rp, ops)


AUTO_ON_CUDA = "pallas-carried"  # what "auto" runs on a CUDA GPU (XLA's loops elsewhere)


def kernel_on(device, kernel: str = "auto") -> str:
    """The form of the Newton step ``kernel`` runs on ``device`` (a jax Device): "auto" is
    :data:`AUTO_ON_CUDA` on a CUDA GPU and "xla" elsewhere; any other form is itself."""
    if kernel != "auto":
        return kernel
    version = str(getattr(getattr(device, "client", None), "platform_version", "")).lower()
    cuda = device.platform in ("gpu", "cuda") and "rocm" not in version
    return AUTO_ON_CUDA if cuda else "xla"


def _factor_flags(in_batched) -> RiccatiFactor:
    """Which factor fields carry the batch (the same for both forms): all but the model
    M = [B, A], which is shared when A and B are (the batch engine's slots share one model,
    and the kernels then read it once per tile instead of a copy per problem)."""
    bA, bB = in_batched[:2]
    return RiccatiFactor(bool(bA or bB), True, True, True)


def _packed_flags(flags: RiccatiFactor) -> RiccatiFactor:
    return flags._replace(Lp=True, Pp=True)


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


_CUDA_TRACE = [None]  # None: from this process's backends; True: forced (tracing_for_cuda)


@functools.cache
def _process_has_gpu() -> bool:
    """Whether this process has a GPU backend (backends do not change once they are up)."""
    try:
        return bool(jax.devices("gpu"))
    except RuntimeError:  # no GPU backend (a CPU-only jaxlib, or no driver)
        return False


def traces_cuda() -> bool:
    """Whether programs traced now keep the CUDA form of the Newton step beside the CPU's (a
    process with a GPU, or inside :func:`tracing_for_cuda`)."""
    forced = _CUDA_TRACE[0]
    return _process_has_gpu() if forced is None else forced


@contextlib.contextmanager
def tracing_for_cuda():
    """Trace the Newton step's CUDA form (the GPU kernels) inside the block whatever devices
    this process has, so that a program traced here can be lowered for a CUDA GPU without one
    (``jax.export`` with ``platforms=["cuda"]``, ``lower(lowering_platforms=("cuda",))``, a
    compile for a described GPU).

    Outside it, a process without a GPU backend traces the CPU's form alone: the form is
    chosen by ``lax.platform_dependent``, which traces every branch, and tracing the kernels'
    entry-wise algebra for programs that can only run on the CPU took a fifth of the time of
    tests/test_paper_mode.py (43 s with it, 34 s without, 2026-11-28). A process with a GPU
    traces both forms, as before. Entering clears JAX's caches when the setting changes: a
    jitted function would otherwise reuse a trace that has only the CPU's form. (Traces made
    inside the block keep both forms; reused on the CPU afterwards, they lower its form.)"""
    old = _CUDA_TRACE[0]
    if not traces_cuda():
        jax.clear_caches()
    _CUDA_TRACE[0] = True
    try:
        yield
    finally:
        _CUDA_TRACE[0] = old


def cuda_or_default(*args, cuda, default):
    """``cuda(*args)`` where the program runs on a CUDA GPU, ``default(*args)`` elsewhere
    (``lax.platform_dependent``, decided when the program is lowered for its device); a
    process that cannot lower for a GPU traces ``default`` alone (:func:`tracing_for_cuda`)."""
    if not traces_cuda():
        return default(*args)
    return lax.platform_dependent(*args, cuda=cuda, default=default)


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
    :class:`ModelTable`, which the kernels' rules read where it is shared and its index
    batched, and everything else ignores."""
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
    differentiated, and a :class:`ModelTable`, the last primal, only repeats A and B), the
    factor of ``op`` with the kernels' storage where ``kernel``'s has it."""

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
        table: a :class:`ModelTable` whose entry is [B, A], or None: under ``vmap`` with the
            table shared and its index batched, the kernels read the model from it.
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
# (rvdjax.solver.primal_dual.PDState.system)
SYSTEM_CARRIED = tuple(k for k, form in PALLAS_FORMS.items() if form.rows and form.carried)


@functools.partial(jax.custom_jvp, nondiff_argnums=(6,))
def riccati_apply_refined(
    f: RiccatiFactor, Phi_u, Phi_x, g_u, g_x, rp, kernel: str = "pallas-block-fused", table=None
) -> NewtonStep:
    """:func:`riccati_apply` and one step of iterative refinement against the KKT matrix of
    ``f`` and the Hessian blocks Phi_u, Phi_x (:func:`newton_residual`, then one more solve):
    with a kernel of :data:`REFINED_IN_KERNEL`, one kernel that forms the residual inside its
    sweeps. ``kernel`` and ``table`` as :func:`riccati_factor`."""
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
        The :class:`NewtonStep`. Non-finite entries signal a failed factorisation.
    """
    return riccati_factor_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, kernel)[1]
