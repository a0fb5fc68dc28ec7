"""The accurate mode's primal-dual iteration on the GPU kernels: where the Newton step's form
runs the inequality rows in kernels (:data:`rvdjax.solver.riccati.ROWS_IN_KERNEL`), the
Newton system, the corrector's right-hand side, the step and the start's drift by
:mod:`rvdjax.solver.rows_kernel` (compiled on a CUDA GPU, interpreted elsewhere), with the
same arguments and results as XLA's forms in :mod:`rvdjax.solver.pd_algebra`."""

from __future__ import annotations

import functools

import jax.numpy as jnp

from rvdjax.solver import rows_kernel
from rvdjax.solver.lanes import tri_unpack
from rvdjax.solver.pd_algebra import SIGMA_FLOOR, SIGMA_FLOOR_RES, PDState, _system_xla
from rvdjax.solver.platform import AUTO_ON_CUDA, cuda_or_default, traces_cuda
from rvdjax.solver.riccati import ROWS_BLOCK_IO, ROWS_IN_KERNEL, SYSTEM_CARRIED, SymStored
from rvdjax.solver.start import drift
from rvdjax.solver.types import SolverSettings

__all__ = ["carries_system", "pd_system", "pd_drift"]


def _kernel_model(ocp, table):
    """The model [B, A] of the blocks' and the step's kernels (as the Riccati kernels' rules
    form it; unused, and not formed, where the kernels read the tables) and their tables
    (Fu, wx, rho, Q, R, [B, A], index) where ``table`` has them all, else ()."""
    model = jnp.concatenate([ocp.B, ocp.A], axis=-1)
    if table is None or table.Fu is None or table.Q is None:
        return model, ()
    return model, (table.Fu, table.x_mask, table.rho, table.Q, table.R, table.M, table.index)


def _blocks_in_kernel(ocp, rows, st: PDState, su, sx, interpret, table=None, block_io=True):
    """:func:`pd_algebra._newton_blocks` by :func:`rows_kernel.pd_blocks`, one kernel that reads Fx
    once and forms the cost's gradient too, and the dynamics' residual in a second sweep (the input
    rows' targets are zero: g_u is base_u). ``table``: the model's table, whose input rows, soft
    rows' mask and penalty, cost blocks and model [B, A] the kernel reads where it has them all;
    ``block_io``: as :func:`rvdjax.solver.rows_kernel.batched`."""
    return _system_blocks(_system_in_kernel(ocp, rows, st, su, sx, interpret, table, block_io))


def _system_in_kernel(ocp, rows, st: PDState, su, sx, interpret, table=None, block_io=True):
    """The Newton system as :func:`rows_kernel.pd_blocks` returns it
    (:attr:`pd_algebra.PDState.system`; arguments as :func:`_blocks_in_kernel`)."""
    del sx  # the kernel forms s - g itself
    model, tables = _kernel_model(ocp, table)
    fn = rows_kernel.batched("blocks", 0, None, interpret, bool(tables), block_io)
    cost = (ocp.Q, ocp.R, model, ocp.q, ocp.r, ocp.x_ref, ocp.c, ocp.x0[None])
    return tuple(fn(*_kernel_rows(rows, st, su), st.u, st.x, *cost, *tables))


def _system_blocks(system):
    """:func:`pd_algebra._newton_blocks`'s (Phi_u, Phi_x, g_u, g_x, base_u, base_x, rp) from a
    system as :attr:`pd_algebra.PDState.system` holds it, Phi_u and Phi_x as :class:`SymStored` (the
    kernels read the triangles; the matrices are for XLA's forms)."""
    Phi_u, Phi_x, g_x, base_u, base_x, rp = system
    Phi_u, Phi_x = (SymStored(tri_unpack(a, 1, True), a) for a in (Phi_u, Phi_x))
    return Phi_u, Phi_x, base_u, g_x, base_u, base_x, rp


def carries_system(settings: SolverSettings) -> bool:
    """Whether the solve's state carries the Newton system (:attr:`pd_algebra.PDState.system`): the
    accurate mode with a form of :data:`rvdjax.solver.riccati.SYSTEM_CARRIED`, or with ``"auto"``
    where that is what it runs on a CUDA GPU and the program keeps the CUDA form
    (:func:`rvdjax.solver.platform.traces_cuda`; on a CPU-only process, never)."""
    if settings.mode != "accurate":
        return False
    if settings.kernel == "auto":
        return AUTO_ON_CUDA in SYSTEM_CARRIED and traces_cuda()
    return settings.kernel in SYSTEM_CARRIED


def pd_system(ocp, rows, st: PDState, kernel: str, table=None):
    """The Newton system at ``st`` (:attr:`pd_algebra.PDState.system`), by the blocks' kernel where
    the Newton step runs on the GPU kernels, else by XLA (a start's; the iterations form the next
    one in their step's kernel). ``table`` as :func:`_blocks_in_kernel`."""
    args = (ocp, rows, st, st.su, st.s - st.g)
    return _by_kernel(args, kernel, _system_xla, functools.partial(_system_in_kernel, table=table))


def _kernel_rows(rows, st: PDState, su):
    """The row arrays the row kernels read (rvdjax.solver.rows_kernel.stage.StageRows)."""
    return (rows.Fx, rows.Fu, st.s, st.g, st.mu, st.pi, rows.wx, rows.rho, su, st.lam, rows.wu)


def _row_tables(table) -> tuple:
    """The row kernels' tables (Fu, wx, rho, index) of a model table that has them, or ()."""
    if table is None or table.Fu is None:
        return ()
    return (table.Fu, table.x_mask, table.rho, table.index)


def _rows_in_kernel(
    rows, st: PDState, base_u, base_x, su, sx, step, h, m_eff, interpret, table=None, block_io=True
):
    """:func:`pd_algebra._corrector_rhs` by :mod:`rvdjax.solver.rows_kernel` (which reads the input
    rows and the soft rows' mask and penalty from ``table``'s, where it has them)."""
    rule = rows_kernel.SigmaRule(SIGMA_FLOOR, SIGMA_FLOOR_RES)
    tables = _row_tables(table)
    fn = rows_kernel.batched("rows", 3, rule, interpret, bool(tables), block_io)
    m_eff = jnp.asarray(m_eff, st.gap.dtype)
    return fn(
        *_kernel_rows(rows, st, su),
        step.dx,
        step.du,
        base_x,
        base_u,
        st.gap,
        st.res,
        m_eff,
        *tables,
    )


def _by_kernel(args, kernel: str, xla, in_kernel):
    """``xla(*args)``, or ``in_kernel(*args, interpret=...)`` where the Newton step runs on
    the GPU kernels of :data:`ROWS_IN_KERNEL` (compiled on a CUDA GPU, interpreted elsewhere,
    as riccati.ops._by_platform chooses; ``kernel="auto"``: compiled on a CUDA GPU, XLA's form
    elsewhere)."""
    on_cuda = AUTO_ON_CUDA if kernel == "auto" else kernel
    # the row kernels' loads and stores: a stage's blocks in the block form's name
    in_kernel = functools.partial(in_kernel, block_io=on_cuda in ROWS_BLOCK_IO)
    compiled = functools.partial(in_kernel, interpret=False)
    if kernel == "auto":
        if AUTO_ON_CUDA not in ROWS_IN_KERNEL:
            return xla(*args)
        return cuda_or_default(*args, cuda=compiled, default=xla)
    if kernel in ROWS_IN_KERNEL:
        interpreted = functools.partial(in_kernel, interpret=True)
        return cuda_or_default(*args, cuda=compiled, default=interpreted)
    return xla(*args)


def pd_drift(ocp, u, kernel: str):
    """The states of the inputs ``u`` from x0 (:func:`rvdjax.solver.start.drift`): one kernel
    where the Newton step's form ``kernel`` runs the rows in kernels (compiled on a CUDA GPU,
    interpreted elsewhere; ``"auto"`` runs XLA's loop on the CPU), else XLA's."""
    return _by_kernel((ocp, u), kernel, drift, _drift_in_kernel)


def _drift_in_kernel(ocp, u, interpret, block_io=True):
    return rows_kernel.drift_batched(interpret, block_io)(ocp.A, ocp.B, ocp.c, u, ocp.x0)


def _step_in_kernel(
    ocp,
    rows,
    st: PDState,
    su,
    sx,
    step,
    taus,
    h,
    fraction,
    aff,
    interpret,
    table=None,
    block_io=True,
    system=False,
):
    """:func:`pd_algebra._step_xla` by :func:`rows_kernel.pd_step_rows`, which also takes the step
    and forms the stopping test's terms (``aff``: the predictor's Fdu_a, Fdx_a, alpha_a, kappa, from
    which it forms the targets ``taus`` and ``h`` again; ``table`` as :func:`_blocks_in_kernel`,
    whose model [B, A] it reads too); with ``system``, also the Newton system at the new point
    (:func:`pd_algebra._step_xla_system`)."""
    Fdu_a, Fdx_a, alpha_a, kappa = aff
    model, tables = _kernel_model(ocp, table)
    kind = "step_system" if system else "step"
    fn = rows_kernel.batched(kind, 3, None, interpret, bool(tables), block_io)
    extra = (ocp.c, ocp.x0[None]) if system else ()
    out = fn(
        *_kernel_rows(rows, st, su),
        step.dx,
        step.du,
        step.nu,
        Fdx_a,
        Fdu_a,
        st.u,
        st.x,
        st.nu,
        ocp.Q,
        ocp.R,
        model,
        ocp.q,
        ocp.r,
        ocp.x_ref,
        *extra,
        alpha_a,
        kappa,
        fraction,
        *tables,
    )
    new, sc, finite = out[:3]
    _, gap_n, rel_d, J = sc
    return (new, gap_n, finite, (rel_d, J), *out[3:])
