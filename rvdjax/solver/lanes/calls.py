"""The Riccati kernels launched over tiles of a batch: :func:`factor`, :func:`factor_solve`,
:func:`apply` and :func:`apply_refined`."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from rvdjax.solver.lanes.config import (
    KernelConfig,
)
from rvdjax.solver.lanes.kernels import (
    _kernel,
    _refined_kernel,
)
from rvdjax.solver.lanes.packing import (
    tri_size,
)


def _compiler_params(cfg: KernelConfig):
    if cfg.interpret:
        return None
    from jax.experimental.pallas import triton as pltr

    return pltr.CompilerParams(num_warps=cfg.num_warps, num_stages=1)


def tile(b: int, block: int) -> tuple[int, int]:
    """(problems a program, the batch padded to whole programs) for a batch of ``b``: tiles
    of ``block`` problems, or, for a batch smaller than a tile, one tile of the next power of
    two (Triton's blocks are powers of two). A problem alone is a tile of one: every launch
    of a padded batch pads each input and slices each output, 59 launches an iteration of
    one fastmpc-3d QP beside the kernels' 8 (``sweeps/gpu_traffic.py solve --batch 1``)."""
    lanes = min(block, 1 << max(b - 1, 0).bit_length())
    return lanes, -(-b // lanes) * lanes


def _pad(a, b_pad):
    """Pad the trailing batch axis to ``b_pad`` by repeating the last problem (padding lanes
    then compute a real problem's numbers: no NaN, nothing to mask)."""
    b = a.shape[-1]
    if b == b_pad:
        return a
    return jnp.concatenate([a, jnp.broadcast_to(a[..., -1:], (*a.shape[:-1], b_pad - b))], -1)


def _call(
    cfg: KernelConfig, factorise: bool, with_rhs: bool, M, mats, rhs, refine=False, index=None
):
    """The kernel's launch. ``M``: the stages' [B, A] of each problem (N, nx, nu + nx, b), of
    all (N, nx, nu + nx), or (``index``, (b,) int) a table (K, N, nx, nu + nx) of K models
    and the one each problem runs."""
    from jax.experimental import pallas as pl

    tabled = index is not None
    if tabled:
        M_table, M = M, M[0]
    N, nx, nu = M.shape[0], M.shape[1], M.shape[2] - M.shape[1]
    b = mats[-1].shape[-1]
    block_io = cfg.block_io and (factorise or cfg.solve_block_io)
    lanes, b_pad = tile(b, cfg.block)
    model_batched = M.ndim == 4
    if model_batched:
        M = _pad(M, b_pad)
    mats = [_pad(m, b_pad) for m in mats]
    rhs = [_pad(r, b_pad) for r in rhs]
    dtype = mats[-1].dtype

    def spec(shape, batched=True):
        n = len(shape)
        if not batched:
            return pl.BlockSpec(tuple(shape), lambda i: (0,) * n)
        return pl.BlockSpec((*shape[:-1], lanes), lambda i: (0,) * (n - 1) + (i,))

    out_shapes = []
    if factorise:  # L and P as their lower triangles (pack)
        out_shapes += [(N, tri_size(nu)), (N, tri_size(nx))]
    if with_rhs:
        out_shapes += [(N, nu), (N, nx), (N, nx)]
    if refine:  # the correction's g_u, p and dynamics residual between its sweeps
        out_shapes += [(N, nu), (N, nx), (N, nx)]
    entries = [s[1:] for s in out_shapes]
    padded = cfg.padded_blocks
    if block_io:  # [stage][entry][problem] (the entries padded to a power of two: padded)
        flat = functools.partial(_flat, padded=padded)
        M = flat(M) if model_batched else M
        mats, rhs = [flat(m) for m in mats], [flat(r) for r in rhs]
        out_shapes = [(N, _entries(math.prod(e), padded)) for e in entries]
    out_shapes = [jax.ShapeDtypeStruct((*s, b_pad), dtype) for s in out_shapes]
    model = "tabled" if tabled else "batched" if model_batched else "shared"
    ins = [M, *mats, *rhs]
    specs = [spec(M.shape, model_batched)] + [spec(a.shape) for a in ins[1:]]
    if tabled:  # the table, flattened as a block array's stages are, then the indices
        K = M_table.shape[0]
        M_table = M_table.reshape(K, N, nx * (nu + nx)) if block_io else M_table
        ins = [M_table, _pad(index.astype(jnp.int32), b_pad), *ins[1:]]
        specs = [spec(M_table.shape, False), spec((b_pad,)), *specs[1:]]
    if refine:
        kernel = functools.partial(_refined_kernel, N, nx, nu, lanes, block_io, padded, model)
    else:
        model_only = block_io and cfg.model_blocks_only
        kernel = functools.partial(
            _kernel, N, nx, nu, lanes, with_rhs, factorise, block_io, padded, model, model_only
        )
    res = pl.pallas_call(
        kernel,
        out_shape=out_shapes,
        grid=(b_pad // lanes,),
        in_specs=specs,
        out_specs=[spec(s.shape) for s in out_shapes],
        interpret=cfg.interpret,
        compiler_params=_compiler_params(cfg),
        name="rvdjax_riccati"
        + ("_factor" if factorise else "")
        + ("_solve" if with_rhs else "")
        + ("_refined" if refine else ""),
    )(*ins)
    if refine:
        res, entries = res[:3], entries[:3]
    if block_io:
        res = [
            r[:, : math.prod(e)].reshape(N, *e, b_pad) for r, e in zip(res, entries, strict=True)
        ]
    return [r[..., :b] for r in res]


def _entries(n: int, padded: bool) -> int:
    """Entries a stage of a block array holds: n, or n padded to a power of two."""
    return 1 << (n - 1).bit_length() if padded else n


def _flat(a, padded: bool = False):
    """(N, entries..., b) -> (N, E, b): a reshape, or a padded copy (``padded``)."""
    e = math.prod(a.shape[1:-1])
    a = a.reshape(a.shape[0], e, a.shape[-1])
    return jnp.pad(a, ((0, 0), (0, _entries(e, padded) - e), (0, 0)))


def factor(M, Phi_u, Phi_x, cfg: KernelConfig = KernelConfig(), index=None):
    """Backward Riccati factorisation: (L, P), each ``[stage][entry][problem]``, L
    and P as their lower triangles (:func:`~rvdjax.solver.lanes.packing.pack`;
    :func:`~rvdjax.solver.lanes.packing.unpack` gives the matrices).

    Args:
        M: (N, nx, nu + nx[, b]) the stages' [B_t, A_t] (no batch axis: shared), or with
            ``index`` a table (K, N, nx, nu + nx) of K models.
        Phi_u: (N, tri(nu), b), Phi_x: (N, tri(nx), b) the Hessian blocks' lower triangles
            (:func:`~rvdjax.solver.lanes.packing.tri_pack`; symmetric, so nothing is lost).
        index: (b,) int, the model of each problem in the table ``M`` (the same arithmetic
            as ``M[index]`` moved batch last, without that copy).
    """
    return tuple(_call(cfg, True, False, M, [Phi_u, Phi_x], [], index=index))


def factor_solve(M, Phi_u, Phi_x, g_u, g_x, rp, cfg: KernelConfig = KernelConfig(), index=None):
    """Factorisation and the step of one right-hand side in one kernel:
    ((L, P), (du, dx, nu)); g_u (N, nu, b), g_x and rp (N, nx, b); ``M`` and
    ``index`` as :func:`factor`."""
    out = _call(cfg, True, True, M, [Phi_u, Phi_x], [g_u, g_x, rp], index=index)
    return tuple(out[:2]), tuple(out[2:])


def apply(M, L, P, g_u, g_x, rp, cfg: KernelConfig = KernelConfig(), index=None):
    """The step (du, dx, nu) of one right-hand side with a stored factorisation (L,
    P as :func:`factor` returns them, packed; ``M`` and ``index`` as :func:`factor`)."""
    return tuple(_call(cfg, False, True, M, [L, P], [g_u, g_x, rp], index=index))


def apply_refined(
    M, L, P, Phi_u, Phi_x, g_u, g_x, rp, cfg: KernelConfig = KernelConfig(), index=None
):
    """The step (du, dx, nu) of one right-hand side with a stored factorisation (packed, as
    :func:`factor` returns it), plus one step of iterative refinement
    (:func:`rvdjax.solver.kkt.kkt_refine`) in the same kernel: the residual needs the Hessian
    blocks Phi_u and Phi_x too, as :func:`factor` takes them (``M`` and ``index`` as
    :func:`factor`)."""
    mats = [L, P, Phi_u, Phi_x]
    return tuple(_call(cfg, False, True, M, mats, [g_u, g_x, rp], True, index=index))
