"""The row kernels launched over tiles of problems, for a batch and under ``vmap``:
:func:`pd_rows`, :func:`pd_step_rows`, :func:`pd_blocks` and :func:`batched`."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from rvdjax.solver import lanes
from rvdjax.solver.lanes import tri_size
from rvdjax.solver.lanes.calls import _compiler_params, _pad
from rvdjax.solver.lanes.refs import _Block, _Entries, _Gathered
from rvdjax.solver.rows_kernel.blocks import _blocks_kernel
from rvdjax.solver.rows_kernel.predictor import _rows_kernel
from rvdjax.solver.rows_kernel.stage import (
    SigmaRule,
    _Shared,
)
from rvdjax.solver.rows_kernel.step import _step_kernel


def _launch(body, name, ins, outs, interpret, tables=None, aliases=None, shared=(), block_io=True):
    """A kernel over tiles of problems: ``ins`` batch-last (N, ..., b) arrays, flattened a
    stage; ``outs`` the (N, entries) of each output; returns them (N, entries, b).
    ``tables``: (index (b,), {position: table (K, N, ...)}): the inputs at those positions
    are read from the tables at each problem's index instead (their ``ins`` are not used).
    ``aliases``: {input position: output position} written in the input's buffer (the kernel
    reads each stage of such an input before it writes that stage of the output).
    ``shared``: positions of inputs that may come without the problem axis, shared by the
    batch (:class:`~rvdjax.solver.rows_kernel.stage._Shared`): those given with one dimension less
    than the problem's (N, e). ``block_io``: the per-problem arrays and the tables read and written
    a stage's block at a time (:class:`rvdjax.solver.lanes.refs._Block`), else entry by entry
    (:class:`rvdjax.solver.lanes.refs._Entries`)."""
    from jax.experimental import pallas as pl

    b = ins[0].shape[-1]
    shared = {i for i in shared if ins[i].ndim == 2}
    cfg = dataclasses.replace(lanes.default_config(), interpret=interpret)
    L, b_pad = lanes.tile(b, cfg.block)
    index, by_pos = tables if tables is not None else (None, {})
    ins = [
        by_pos[i].reshape(*by_pos[i].shape[:2], -1)
        if i in by_pos
        else a.reshape(a.shape[0], -1)
        if i in shared
        else _pad(a.reshape(a.shape[0], -1, b), b_pad)
        for i, a in enumerate(ins)
    ]
    out_shape = [jax.ShapeDtypeStruct((*o, b_pad), ins[0].dtype) for o in outs]

    def spec(shape, batched=True):
        n = len(shape)
        if not batched:
            return pl.BlockSpec(tuple(shape), lambda i: (0,) * n)
        return pl.BlockSpec((*shape[:-1], L), lambda i: (0,) * (n - 1) + (i,))

    specs = [spec(a.shape, i not in by_pos and i not in shared) for i, a in enumerate(ins)]
    if index is not None:  # the tile's indices, the last input
        ins, specs = [*ins, _pad(index.astype(jnp.int32), b_pad)], [*specs, spec((b_pad,))]

    def kernel(*refs):
        lane_index = None
        if index is not None:  # the last input: the tile's indices
            n = len(ins) - 1
            lane_index, refs = refs[n][...], refs[:n] + refs[n + 1 :]
        refs = [
            _Gathered(r, lane_index, block_io)
            if i in by_pos
            else _Shared(r)
            if i in shared
            else _Block(r)
            if block_io
            else _Entries(r)
            for i, r in enumerate(refs)
        ]
        return body(*refs)

    out = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(b_pad // L,),
        in_specs=specs,
        out_specs=[spec(o.shape) for o in out_shape],
        interpret=interpret,
        compiler_params=_compiler_params(cfg),
        name=name,
        input_output_aliases=dict(aliases or {}),
    )(*ins)
    return [o[..., :b] for o in out]


def pd_rows(
    rows,
    dx,
    du,
    base_x,
    base_u,
    scalars,
    rule: SigmaRule,
    interpret: bool = False,
    tables=None,
    block_io: bool = True,
):
    """The corrector's right-hand side from the predictor's step, for a batch.

    Args (batch last, b problems): ``rows`` = (Fx (N, mx, nx, b), Fu (N, mu, nu, b), the soft
    rows' slack s, values g = Fx x - fx, multipliers mu, pi, mask wx and penalty rho
    (N, mx, b), the input rows' slack su = fu - Fu u, multiplier lam and mask wu (N, mu, b));
    the predictor's step dx (N, nx, b), du (N, nu, b); the cost gradients base_x (N, nx, b),
    base_u (N, nu, b); scalars: three (b,) arrays, the complementarity gap, the relative
    dual residual and the number of barrier terms; ``rule`` the
    :class:`~rvdjax.solver.rows_kernel.stage.SigmaRule`.

    Returns:
        g_u (N, nu, b), g_x (N, nx, b) the corrector's right-hand side, Fdu (N, mu, b) and
        Fdx (N, mx, b) the predictor's row products, alpha_a (b,) its step length and kappa
        (b,) the corrector's barrier weight.

    ``tables``: None, or (index (b,), Fu (K, N, mu, nu), wx (K, N, mx), rho (K, N, mx)):
    the kernel reads Fu (then zeroed where wu is off), wx and rho from the tables at each
    problem's index instead of from ``rows``. ``block_io``: as :func:`_launch`.
    """
    N, mx, nx, b = rows[0].shape
    mu, nu = rows[10].shape[1], du.shape[1]
    dims = (mx, mu, nx, nu)
    # alpha_a and kappa as outputs of their own: the step's kernel reads them as they are
    _, _, Fdu, Fdx, alpha, kappa, g_u, g_x = _launch(
        functools.partial(_rows_kernel, dims, N, rule),
        "rvdjax_pd_rows",
        [*rows, dx, du, base_x, base_u, *(a[None, None] for a in scalars)],
        [(N, 3 * nu), (N, 3 * nx), (N, mu), (N, mx), (1, 1), (1, 1), (N, nu), (N, nx)],
        interpret,
        _tables("rows", tables),
        block_io=block_io,
    )
    return g_u, g_x, Fdu, Fdx, alpha[0, 0], kappa[0, 0]


#: The inputs that tables can stand for, by kernel, in the order :func:`batched` takes the
#: tables: the rows' Fu, wx, rho, and the cost blocks Q, R and the model [B, A] of
#: :func:`pd_blocks` and :func:`pd_step_rows`.
_TABLE_POSITIONS = {
    "rows": (1, 6, 7),
    "blocks": (1, 6, 7, 13, 14, 15),
    "step": (1, 6, 7, 19, 20, 21),
    "step_system": (1, 6, 7, 19, 20, 21),
}

#: The inputs read as a table of one (index 0) when a batch shares them (unbatched under
#: ``vmap``) and no tables are given: not a copy for every problem.
_SHAREABLE = {"rows": (), "blocks": (13, 14, 15), "step": (19, 20, 21)}
_SHAREABLE["step_system"] = _SHAREABLE["step"]

#: The inputs read as :class:`~rvdjax.solver.rows_kernel.stage._Shared` when a batch shares
#: them, with tables or without: the linear costs q, r, the reference x_ref and the dynamics'
#: offset c (the batch engine's zero linear costs and offsets).
_SHARED = {"rows": (), "blocks": (16, 17, 18, 19), "step": (22, 23, 24)}
_SHARED["step_system"] = (22, 23, 24, 25)  # and the dynamics' offset c


def _tables(kind, tables):
    """_launch's tables from (index, Fu, wx, rho[, ...]) in :data:`_TABLE_POSITIONS`'s order,
    those given (not None)."""
    if tables is None:
        return None
    index, *ts = tables
    positions = _TABLE_POSITIONS[kind]
    return index, {p: t for p, t in zip(positions, ts, strict=False) if t is not None}


def pd_step_rows(
    rows,
    dx,
    du,
    nu_new,
    Fdx_a,
    Fdu_a,
    u,
    x,
    nu,
    cost,
    scalars,
    interpret: bool = False,
    tables=None,
    block_io: bool = True,
    system=None,
):
    """The corrector's step taken, for a batch: its row products, its step length (zero where
    the step or a row's step is not finite, or the solve is stopped), the new iterate, the
    complementarity there and the stopping test's relative dual residual and objective there.

    Args (batch last, b problems): ``rows`` as :func:`pd_rows`; the corrector's step
    dx (N, nx, b), du (N, nu, b) and new multipliers nu_new (N, nx, b); the predictor's row
    products Fdx_a (N, mx, b), Fdu_a (N, mu, b); the iterate's u (N, nu, b), x (N, nx, b) and
    nu (N, nx, b); ``cost`` = (Q (N, nx, nx, b), R (N, nu, nu, b), the model [B, A]
    (N, nx, nu + nx, b), q (N, nx, b), r (N, nu, b), x_ref (N, nx, b)): the cost and the
    model (:class:`rvdjax.ocp.OCP`'s), q, r and x_ref without the problem axis where the
    batch shares them; scalars: three (b,) arrays, the predictor's step length alpha_a, the
    corrector's barrier weight kappa (its targets are kappa - alpha_a dv dy of the predictor's
    steps) and the fraction of the way to the boundary that the step goes
    (pd_algebra.step_fraction; 0 where the solve is stopped).

    Returns:
        new: the new u, x, nu, s, lam, mu, pi, su, g (as the inputs);
        sc (4, b): the step length taken alpha (``fraction`` of the way to the boundary, at most 1;
        NaN in no case: whether the step was finite is ``finite``), the complementarity at the
        new point, the relative dual residual and the objective there
        (pd_algebra._stopping_terms);
        finite (b,) bool: whether every entry of the step and of the rows' steps is finite.

    ``tables``: None, or (index (b,), Fu, wx, rho, Q, R, [B, A]), each table (K, N, ...) or
    None: the kernel reads those given from the tables at each problem's index.
    ``block_io``: as :func:`_launch`. ``system``: None, or (c (N, nx, b), x0 (1, nx, b)), the
    dynamics' offset (without the problem axis where the batch shares it) and the initial
    state: the kernel also forms the next iteration's Newton system at the new point, and
    returns it fourth, as :func:`pd_blocks` returns it.
    """
    N, mx, nx, b = rows[0].shape
    mu, n_u = rows[10].shape[1], du.shape[1]
    dims = (mx, mu, nx, n_u)
    extra, sys_shapes = (), []
    if system is not None:
        extra = tuple(system)
        sys_shapes = [(N, tri_size(n_u)), (N, tri_size(nx)), (N, nx), (N, n_u), (N, nx), (N, nx)]
    kind = "step" if system is None else "step_system"
    _, _, _, _, *out, sc = _launch(
        functools.partial(_step_kernel, dims, N, system is not None),
        "rvdjax_pd_step_rows" if system is None else "rvdjax_pd_step_system",
        [*rows, dx, du, nu_new, Fdx_a, Fdu_a, u, x, nu, *cost, *extra]
        + [a[None, None] for a in scalars],
        # the first sweep's row products and row terms, read back by the second; forming the
        # system, the second sweep forms them again from the rows it reads anyway (placeholders)
        ([(N, 2 * n_u), (N, 2 * nx), (N, mu), (N, mx)] if system is None else [(1, 1)] * 4)
        + [(N, n_u), (N, nx), (N, nx), (N, mx), (N, mu), (N, mx), (N, mx), (N, mu), (N, mx)]
        + sys_shapes
        + [(1, 5)],
        interpret,
        _tables(kind, tables),
        # the new iterate in the old one's buffers: otherwise XLA copies each new array into
        # the solver loop's carry (counted for an H100: 8 copies an iteration, 35 KB a
        # thesis-vbar slot read and written)
        {16: 4, 17: 5, 18: 6, 2: 7, 9: 8, 4: 9, 5: 10, 8: 11, 3: 12},
        _SHARED[kind],
        block_io,
    )
    new, next_system, sc = tuple(out[:9]), tuple(out[9:]), sc[0]
    if system is None:
        return new, sc[:4], sc[4] > 0
    return new, sc[:4], sc[4] > 0, next_system


def pd_blocks(rows, u, x, cost, x0, interpret: bool = False, tables=None, block_io: bool = True):
    """The predictor's Newton system, for a batch: the Hessian blocks Phi_u = 2 R + Fu^T Du Fu
    and Phi_x = 2 Q + Fx^T diag(wx a c / (a + c)) Fx, the cost's gradient base_u = 2 R u + r,
    base_x = 2 Q (x - x_ref) + q, the state part of the right-hand side
    g_x = base_x + Fx^T (wx a rho / (a + c)) (the input part is base_u itself: the input rows'
    targets are zero) and the dynamics' residual rp = x_t - A_t x_{t-1} - B_t u_t - c_t, from
    the rows in one sweep that reads Fx once (XLA: in three passes, two of them reading Fx;
    primal_dual.pd_iteration), the residual in a second sweep of the same kernel.

    Args (batch last, b problems): ``rows`` as :func:`pd_rows`; the iterate's u (N, nu, b),
    x (N, nx, b); ``cost`` = (Q (N, nx, nx, b), R (N, nu, nu, b), the model [B, A]
    (N, nx, nu + nx, b), q (N, nx, b), r (N, nu, b), x_ref (N, nx, b), c (N, nx, b)), the
    last four without the problem axis where the batch shares them; x0 (1, nx, b).

    Returns:
        Phi_u (N, tri(nu), b), Phi_x (N, tri(nx), b) as their lower triangles
        (:func:`rvdjax.solver.lanes.tri_pack`; the Riccati kernels read them so),
        g_x (N, nx, b), base_u (N, nu, b), base_x (N, nx, b), rp (N, nx, b).

    ``tables``: None, or (index (b,), Fu, wx, rho, Q, R, [B, A]) with each table (K, N, ...)
    or None: the kernel reads those given from the tables at each problem's index.
    ``block_io``: as :func:`_launch`.
    """
    N, mx, nx, b = rows[0].shape
    mu, nu = rows[10].shape[1], u.shape[1]
    dims = (mx, mu, nx, nu)
    Pu, Px, g_x, base_u, base_x, rp = _launch(
        functools.partial(_blocks_kernel, dims, N),
        "rvdjax_pd_blocks",
        [*rows, u, x, *cost, x0],
        [(N, tri_size(nu)), (N, tri_size(nx)), (N, nx), (N, nu), (N, nx), (N, nx)],
        interpret,
        _tables("blocks", tables),
        shared=_SHARED["blocks"],
        block_io=block_io,
    )
    return Pu, Px, g_x, base_u, base_x, rp


@functools.cache
def batched(
    kind: str,
    n_scalars: int,
    rule: SigmaRule | None,
    interpret: bool,
    tabled: bool = False,
    block_io: bool = True,
):
    """:func:`pd_rows` (``kind`` "rows"), :func:`pd_step_rows` ("step"; "step_system" with
    its ``system``, the dynamics' offset c and the initial state x0 (1, nx) after the cost)
    or :func:`pd_blocks` ("blocks") for one problem (arrays without the batch axis; a batch
    of one), and under ``vmap`` for the batch (``jax.custom_batching.custom_vmap``);
    unbatched inputs are broadcast. The arguments are the 11 row arrays, the kernel's other
    arrays, then
    ``n_scalars`` scalars a problem, then (``tabled``) the tables of
    :data:`_TABLE_POSITIONS` (Fu, wx, rho; and Q, R for "blocks"; Q, R, A, B for "step") and
    the problem's index, which the kernel reads instead of those arrays where the tables are
    shared and the index batched (:class:`rvdjax.solver.riccati.ModelTable`). Without tables,
    the kernels read the cost blocks and the model of :data:`_SHAREABLE` that a batch shares
    as a table of one, not as a copy for every problem. ``block_io``: as :func:`_launch`."""
    n_tables = len(_TABLE_POSITIONS[kind]) + 1 if tabled else 0

    def run(args, tables=None):
        rows, rest = args[:11], args[11 : len(args) - n_scalars]
        scalars = args[len(args) - n_scalars :]
        if kind == "blocks":
            out = pd_blocks(rows, *rest[:2], rest[2:-1], rest[-1], interpret, tables, block_io)
        elif kind == "rows":
            out = pd_rows(rows, *rest, scalars, rule, interpret, tables, block_io)
        elif kind == "step":
            out = pd_step_rows(rows, *rest[:8], rest[8:], scalars, interpret, tables, block_io)
        else:
            cost, system = rest[8:14], rest[14:]
            out = pd_step_rows(rows, *rest[:8], cost, scalars, interpret, tables, block_io, system)
        return jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), out)

    @jax.custom_batching.custom_vmap
    def fn(*args):
        args = args[: len(args) - n_tables]
        return jax.tree.map(lambda a: a[0], run([a[..., None] for a in args]))

    @fn.def_vmap
    def rule_(axis_size, in_batched, *args):
        n = len(args) - n_tables
        tables = None
        if tabled and not any(in_batched[n:-1]) and in_batched[-1]:
            *ts, index = args[n:]
            tables = (index, *ts)
        elif any(not in_batched[p] for p in _SHAREABLE[kind]):
            one = jnp.zeros((axis_size,), jnp.int32)
            tables = (one,) + tuple(
                None if p not in _SHAREABLE[kind] or in_batched[p] else args[p][None]
                for p in _TABLE_POSITIONS[kind]
            )
        full = [
            a
            if not bt and i in _SHARED[kind]
            else jnp.moveaxis(a if bt else jnp.broadcast_to(a, (axis_size, *a.shape)), 0, -1)
            for i, (a, bt) in enumerate(zip(args[:n], in_batched[:n], strict=True))
        ]
        out = run(full, tables)
        return out, jax.tree.map(lambda _: True, out)

    return fn
