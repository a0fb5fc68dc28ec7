"""The accurate mode's row work as three GPU kernels: before, between and after its two
Newton solves.

Before the first solve, the Newton matrix's diagonal blocks Phi_u = 2 R + Fu^T Du Fu,
Phi_x = 2 Q + Fx^T D Fx and the predictor's right-hand side g_x depend on the rows and their
multipliers; XLA formed them in three passes, two of which read Fx. :func:`pd_blocks` forms
them in one sweep, with the cost's gradient 2 R u + r, 2 Q (x - x_ref) + q at the iterate,
which both right-hand sides share.

Between the predictor's solve and the corrector's, a Mehrotra iteration
(:func:`rvdjax.solver.primal_dual.pd_iteration`) works on the constraint rows only: the
predictor's row steps (F du, F dx and the slack and multiplier steps that follow), its step
length (a ratio test over every row), the complementarity after that step, Mehrotra's sigma
and the corrector's targets, and from them the corrector's right-hand side F^T (...). On a GPU
XLA made that about eight passes through device memory, reading the rows, their multipliers
and the constraint matrix Fx again in most of them (thesis-vbar: 12 soft rows a stage, Fx
17 KB a problem; docs/benchmark.md). Here it is one Pallas kernel (Triton on a GPU,
interpreted on the CPU for the tests), one problem per lane as in :mod:`rvdjax.solver.lanes`,
in one sweep over the stages that reads each stage's rows once (:func:`pd_rows`).

After the corrector's solve the same holds for its row steps, its step length (the ratio
test, NaN where a step is not finite), the update of the iterate itself, the complementarity
at the new point and the stopping test there: the cost gradient, the dual residual (with the
rows' terms Fu^T wu lam, Fx^T wx mu and the model's A^T nu, B^T nu) and the objective
(:func:`pd_step_rows`).

A sweep reads its arrays from device memory (a tile's rows are megabytes; they do not stay in
the cache between sweeps while a hundred tiles run at once), so a kernel sweeps as few times
as it can. The step length and the barrier weight are known only at a sweep's end, so the
sweep sums what depends on them as polynomials: the complementarity after the step,
c0 + alpha c1 + alpha^2 c2, and the right-hand side, G0 + kappa G1 + alpha G2 (the targets
kappa - alpha dv dy are affine in both), evaluated once they are known. The update needs the
step length at every row: the corrector's kernel sweeps a second time for it, reading the
rows but not Fx (the row products it wrote in the first sweep), and writes the new iterate
into the old one's buffers. Where the solve carries the Newton system
(``kernel="pallas-carried"``, the default on a CUDA GPU), that second sweep also forms the
next iteration's blocks and right-hand side at the new iterate, reading Fx again, and the next
iteration starts without :func:`pd_blocks` (:attr:`rvdjax.solver.pd_algebra.PDState.system`).
Otherwise the kernels compute the expressions of
:mod:`rvdjax.solver.pd_algebra`; the results agree with XLA's form to rounding (tests).

Inputs are batch-last and flattened a stage, ``[stage][entry][problem]``; see :func:`pd_rows`.
The kernels read and write them entry by entry, the input rows and then the soft rows one at a
time in loops inside each stage (``kernel="pallas-rows"``, ``"pallas-entries"`` and
``"pallas-carried"``, the default on a CUDA GPU), or a stage's block at a time, every row at once
(``"pallas-block-rows"``): the same arithmetic. A block is split into lane vectors and joined
back through shared memory with a barrier each: assembled by ptxas for an H100, the three
kernels of thesis-vbar's engine held about 1 200 barriers that way, and the step's kernel fell
to 32 registers with 22 KB of spill stores; a stage's 12 rows unrolled entry by entry still
spilled 2-8 KB a kernel. One row at a time, the three hold no barrier and spill nothing
(``sweeps/gpu_registers.py``, docs/benchmark.md). With the input rows one at a time too, the
kernels between and after the solves need 151 and 168 registers instead of 198 and 244 in
thesis-vbar's engine (154 and 168 instead of 218 and 242-254 with 65 536 fastmpc-3d QPs): a
multiprocessor then holds three of their programs instead of two.

The modules: :mod:`~rvdjax.solver.rows_kernel.stage` (a stage's rows as lane vectors, their
steps and their terms in the Newton system), one per kernel program
(:mod:`~rvdjax.solver.rows_kernel.predictor` between the solves,
:mod:`~rvdjax.solver.rows_kernel.step` after them, :mod:`~rvdjax.solver.rows_kernel.blocks`
the Newton system, :mod:`~rvdjax.solver.rows_kernel.drift` the start's drift), and
:mod:`~rvdjax.solver.rows_kernel.calls`, which launches them over tiles of a batch.
"""

from __future__ import annotations

from rvdjax.solver.rows_kernel.calls import batched, pd_blocks, pd_rows, pd_step_rows
from rvdjax.solver.rows_kernel.drift import drift_batched
from rvdjax.solver.rows_kernel.stage import SigmaRule, StageRows, Steps  # noqa: F401  (as before)

__all__ = ["SigmaRule", "pd_rows", "pd_step_rows", "pd_blocks", "batched", "drift_batched"]
