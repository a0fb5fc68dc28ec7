"""The recursion under ``vmap`` by the GPU kernels of :mod:`rvdjax.solver.lanes` (or their
algebra as XLA loops, :mod:`rvdjax.solver.unrolled`): the operands moved to the kernels'
batch-last layout and back."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import jax.scipy.linalg

from rvdjax.solver import lanes, unrolled
from rvdjax.solver.riccati.recursion import (
    NewtonStep,
    RiccatiFactor,
    SymStored,
    _lower,
    whole,
)
from rvdjax.solver.riccati.xla_rules import (
    _factor_flags,
    _full,
    _packed_flags,
    _to_first,
    _to_last,
    _xla_apply_refined_rule,
)
from rvdjax.solver.types import PALLAS_FORMS

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
    one) and None, or the shared ``table`` (:class:`~rvdjax.solver.riccati.recursion.ModelTable`,
    its index batched) and the problems' indices where the model is per problem and the kernels read
    tables (every "pallas*" form; the "unrolled" loops take the copy)."""
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
    against H (riccati.recursion._factor), so the two agree to H's conditioning times rounding."""
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
    lower triangles for the Pallas kernels (:class:`~rvdjax.solver.riccati.recursion.SymStored`'s,
    or packed from the matrices), the matrices for the unrolled loops."""
    if impl == "unrolled":
        return [_to_last(_full(axis_size, whole(a), whole(b))) for a, b in blocks]
    return [_to_last(_full(axis_size, _lower(a, -2), _lower_flag(b))) for a, b in blocks]


def _lower_flag(b):
    """The batch flag of :func:`~rvdjax.solver.riccati.recursion._lower`'s triangles (a
    custom_vmap rule's flags come in the arguments' structure)."""
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
