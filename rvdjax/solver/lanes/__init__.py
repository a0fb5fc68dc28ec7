"""The Riccati factorisation and solves of the Newton step as GPU kernels, one problem per lane.

On a GPU the XLA form of the recursion (:mod:`rvdjax.solver.riccati`) is a ``lax.scan`` over the
horizon whose body becomes several small kernels per stage, every stage's blocks passing
through device memory between them: at 65 536 problems an iteration took ~717 ns per problem
on an H100 where its ~30 KB of traffic needs 10-20 ns (DESIGN §8a). Here the whole recursion
is one Pallas kernel (Triton lowering) per sweep, as the field's batched GPU solvers do
(GATO, CusADi: one instance per thread, the stages in a loop inside the kernel):

* the batch is the minor axis: every array is laid out `[stage][entry][problem]` and a program
  owns a tile of ``BLOCK`` consecutive problems, so each load of one matrix entry is one
  coalesced vector load across the tile;
* the 6x6, 6x3 and 3x3 algebra is written out entry by entry over those lane vectors
  (nested lists of ``(BLOCK,)`` vectors, no ``dot``: float64 MMA needs blocks of 16 and more);
  the cost-to-go P and the affine term p live in registers across the stage loop;
* the factorisation is stored as L and P alone, 27 entries a stage (the Cholesky factor
  and the symmetric P as their lower triangles, :func:`pack`), written once and read back by
  the solves' sweeps with the backward sweep's p; the kernels read the Hessian blocks Phi_x
  and Phi_u as their triangles too (21 and 6 entries). No gain is stored: a backward sweep
  forms p_t = g_x + A^T (q + P B k) (:func:`_backward_rhs_stored`) and a forward sweep solves
  each stage again, du = -H^-1 (g_u + B^T (p + P (A dx - r))) (:func:`_forward_solved`),
  where the textbook recursion stores K and B^T P A (36 more entries a stage, read in every
  sweep: on a GPU each sweep reads them from device memory).

Four kernels: :func:`factor_solve` (the backward factorisation together with the backward
sweep of the first right-hand side, then its forward sweep), :func:`apply` (one more
right-hand side with a stored factorisation), :func:`apply_refined` (that, then one step of
iterative refinement with the residual formed inside the sweeps) and :func:`factor` (no
right-hand side). The factorisation is :mod:`rvdjax.solver.riccati`'s recursion in the same
order (the Joseph form, the gain K refined once against H, kept in registers); the solves
are the same step written without the gain, so their results agree with the XLA form to
rounding (tests: 1e-10 and the same iteration counts on fastmpc-3d and the random
classes); ``interpret=True`` runs them on the CPU for the tests. They run with
``SolverSettings(kernel="pallas")`` (or another of the forms of
:data:`rvdjax.solver.types.PALLAS_FORMS`, through :class:`KernelConfig`), and
``kernel="auto"`` runs ``"pallas-carried"`` when a program is compiled for a CUDA GPU: an
accurate-mode iteration is then the factorisation with the predictor's step (the model
[B, A] read in blocks), the row work between the solves (:mod:`rvdjax.solver.rows_kernel`),
the corrector's step with its refinement, and its row work with the next iteration's Newton
blocks, every other operand entry by entry. The other forms call :func:`factor` then
:func:`apply` (and :func:`apply` again for the refinement): on one H200 (jax 0.11.2, CUDA 13,
2026-11-26) Triton compiled the entry-wise :func:`factor` in 51 s and :func:`apply` in about
3 s, where the entry-wise :func:`factor_solve` had not finished in 165 s on an H100; with
block loads and stores the factorisation compiles in seconds (docs/solver.md).

Inputs are batch-last: ``A`` (N, nx, nx[, b]), ``B`` (N, nx, nu[, b]) (without the batch
axis when the model is shared by every problem), ``Phi_u`` (N, tri(nu), b), ``Phi_x``
(N, tri(nx), b) (lower triangles, :func:`tri_pack`), right-hand sides ``g_u`` (N, nu, b),
``g_x``, ``rp`` (N, nx, b). The batch is padded to a multiple of ``BLOCK`` inside.

The modules: :mod:`~rvdjax.solver.lanes.config` (the launch configuration),
:mod:`~rvdjax.solver.lanes.calls` (the four kernels launched over a batch's tiles),
:mod:`~rvdjax.solver.lanes.kernels` (their programs, one tile each),
:mod:`~rvdjax.solver.lanes.stage` (a stage of the recursion's sweeps, which the unrolled XLA form
shares), :mod:`~rvdjax.solver.lanes.algebra` (the small-matrix algebra over lane vectors),
:mod:`~rvdjax.solver.lanes.refs` (a kernel's arrays loaded and stored a stage at a time) and
:mod:`~rvdjax.solver.lanes.packing` (matrices stored as their lower triangles).
"""

from __future__ import annotations

from rvdjax.solver.lanes.algebra import chol, chol_solve
from rvdjax.solver.lanes.calls import apply, apply_refined, factor, factor_solve, tile
from rvdjax.solver.lanes.config import KernelConfig, configured, default_config
from rvdjax.solver.lanes.packing import pack, tri_pack, tri_size, tri_unpack, unpack

__all__ = [
    "KernelConfig",
    "configured",
    "default_config",
    "chol",
    "chol_solve",
    "factor",
    "factor_solve",
    "apply",
    "apply_refined",
    "pack",
    "unpack",
    "tri_size",
    "tri_pack",
    "tri_unpack",
    "tile",
]
